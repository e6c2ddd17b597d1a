"""Ellipses between their wire and file forms (`EllipsoidMsg`, `EllipseModel`) and the geometry the cores
compute with: the models know no geometry, so the conversions live here, above both."""

from __future__ import annotations

from schemas.files import EllipseModel
from schemas.messages import EllipsoidMsg, Header
from services.geometry import Ellipse


def ellipse_to_msg(ellipse: Ellipse, *, group: int, cluster_id: int) -> EllipsoidMsg:
    (a11, a12), (a21, a22) = ellipse.A.tolist()
    # Ellipse symmetrises A; write the mean of the off-diagonals so the message is exactly symmetric.
    off = 0.5 * (a12 + a21)
    return EllipsoidMsg(
        A=((a11, off), (off, a22)), b=tuple(ellipse.b.tolist()), group=group, cluster_id=cluster_id
    )


def ellipses_from_msgs(messages: list[EllipsoidMsg]) -> list[Ellipse]:
    return [Ellipse(A=msg.A, b=msg.b) for msg in messages]


def ellipse_to_model(ellipse: Ellipse) -> EllipseModel:
    """The ellipse as `plan.json` writes it (CONTRACTS §4): A and b as computed."""
    A = ellipse.A.tolist()
    return EllipseModel(A=(tuple(A[0]), tuple(A[1])), b=tuple(ellipse.b.tolist()))


def ellipse_from_model(model: EllipseModel) -> Ellipse:
    return Ellipse(A=model.A, b=model.b)


def answer_header(*, scan_header: Header, seq: int) -> Header:
    """Header of a stage output: the scan's stamp (sim time) so every status and output of one scan
    carries the same stamp, and the publishing stage's own sequence number."""
    return Header(stamp_s=scan_header.stamp_s, frame_id=scan_header.frame_id, seq=seq)
