"""Message models: JSON round trip, rejection of bad input, wiring table and schema export."""

from __future__ import annotations

import base64
import json
import math
import re
import zlib

import pytest
from pydantic import BaseModel, ValidationError

from schemas.export import export_json_schemas
from schemas.messages import (
    MESSAGE_MODELS,
    CircleMsg,
    ClusterMsg,
    Clusters,
    DecodeError,
    EllipsoidMsg,
    Ellipsoids,
    Goals,
    Header,
    Map,
    Pose2D,
    RawPath,
    RobotState,
    Scan,
    SmoothPath,
    StageStatus,
    World,
    decode,
    encode,
)
from schemas.wiring import (
    MONITOR,
    PROCESSES,
    ROS2,
    SIM,
    STAGES,
    TOPICS,
    alive_key,
    default_prefix,
    key,
    model_for,
    publishers_of,
    stage_of_alive_key,
    stage_of_status_key,
    status_key,
)

HEADER = Header(stamp_s=1.5, seq=3)
ELLIPSE = EllipsoidMsg(A=((2.0, 0.5), (0.5, 1.0)), b=(-1.0, 0.25), group=0, cluster_id=4)

EXAMPLES: dict[type[BaseModel], BaseModel] = {
    Scan: Scan(header=HEADER, pose=Pose2D(x_m=1.0, y_m=2.0, theta_rad=0.3), points=[(3.0, 4.0)]),
    Clusters: Clusters(
        header=HEADER,
        scan_seq=3,
        clusters=[ClusterMsg(cluster_id=4, points=[(3.0, 4.0), (3.1, 4.0)], solid=True)],
    ),
    Ellipsoids: Ellipsoids(header=HEADER, scan_seq=3, inflation_m=0.65, ellipsoids=[ELLIPSE]),
    RawPath: RawPath(
        header=HEADER, scan_seq=3, status="ok", goal_index=0,
        points=[(0.0, 0.0), (10.0, 10.0)], ellipsoids=[ELLIPSE],
    ),
    SmoothPath: SmoothPath(
        header=HEADER, scan_seq=3, status="no_path", goal_index=1, points=[],
        max_curvature=0.0, min_level=1.2,
    ),
    RobotState: RobotState(
        header=HEADER, pose=Pose2D(x_m=0.0, y_m=0.0, theta_rad=0.0), speed_mps=0.5,
        steering_rad=-0.1, goal_index=1, goals_reached=1, done=False,
    ),
    Goals: Goals(header=HEADER, goals=[(10.0, 10.0), (15.0, 15.0)]),
    StageStatus: StageStatus(
        header=HEADER, stage="planner", state="error", reason="solver failed",
        input_key="cvxnav/robot1/ellipsoids", processing_ms=12.5,
    ),
    World: World(
        header=HEADER, scenario="paper", bounds_min=(-1.0, -1.0), bounds_max=(20.0, 20.0),
        robot_width_m=0.3, robot_length_m=0.6, start=Pose2D(x_m=0.0, y_m=0.0, theta_rad=0.0),
        goals=[(10.0, 10.0)], goal_tolerance_m=0.3, polygons=[[(1.0, 1.0), (2.0, 1.0), (2.0, 2.0)]],
        circles=[CircleMsg(center=(5.0, 5.0), radius_m=1.0)],
    ),
    Map: Map(header=HEADER, width=3, height=2, resolution_m=0.05, origin=Pose2D(x_m=-1.0, y_m=2.0, theta_rad=0.1),
             cells=Map.pack_cells(bytes([0, 1, 2, 0, 0, 1]))),
}


def test_every_model_has_an_example():
    assert set(EXAMPLES) == set(MESSAGE_MODELS)


@pytest.mark.parametrize("model", MESSAGE_MODELS, ids=lambda m: m.__name__)
def test_json_round_trip(model):
    message = EXAMPLES[model]
    assert decode(model, encode(message), encoding=model.encoding()) == message


@pytest.mark.parametrize("model", MESSAGE_MODELS, ids=lambda m: m.__name__)
def test_encoding_names_schema_and_version(model):
    assert model.encoding() == f"application/json;cvxnav.{model.__name__}/{model.VERSION}"


def test_models_are_frozen():
    with pytest.raises(ValidationError):
        HEADER.seq = 4  # type: ignore[misc]


def _scan_json(**overrides) -> dict:
    doc = json.loads(encode(EXAMPLES[Scan]))
    doc.update(overrides)
    return doc


def test_decode_rejects_invalid_json():
    with pytest.raises(DecodeError, match="invalid JSON"):
        decode(Scan, b'{"header": ')


def test_decode_rejects_nan_naming_the_field():
    payload = json.dumps(_scan_json(points=[[1.0, math.nan]])).encode()
    with pytest.raises(DecodeError, match=r"points\.0\.1: Input should be a finite number"):
        decode(Scan, payload)


def test_decode_rejects_unknown_field():
    payload = json.dumps(_scan_json(extra_field=1)).encode()
    with pytest.raises(DecodeError, match="extra_field"):
        decode(Scan, payload)


def test_decode_rejects_wrong_schema_by_encoding():
    with pytest.raises(DecodeError, match="wrong schema: expected cvxnav.Scan/1, got cvxnav.Clusters/1"):
        decode(Scan, encode(EXAMPLES[Clusters]), encoding=Clusters.encoding())


def test_decode_rejects_wrong_schema_by_content():
    with pytest.raises(DecodeError) as error:
        decode(Scan, encode(EXAMPLES[Clusters]))
    assert "\n" not in str(error.value)


def test_decode_rejects_other_version():
    with pytest.raises(DecodeError, match="wrong schema"):
        decode(Scan, encode(EXAMPLES[Scan]), encoding="application/json;cvxnav.Scan/2")


@pytest.mark.parametrize(
    "matrix",
    [((1.0, 0.2), (0.3, 1.0)), ((1.0, 2.0), (2.0, 1.0)), ((-1.0, 0.0), (0.0, -1.0)), ((0.0, 0.0), (0.0, 1.0))],
    ids=["asymmetric", "indefinite", "negative-definite", "singular"],
)
def test_ellipsoid_matrix_must_be_spd(matrix):
    with pytest.raises(ValidationError, match="A must be"):
        EllipsoidMsg(A=matrix, b=(0.0, 0.0), group=0, cluster_id=0)


def test_negative_stamp_and_empty_cluster_rejected():
    with pytest.raises(ValidationError):
        Header(stamp_s=-0.1, seq=0)
    with pytest.raises(ValidationError):
        ClusterMsg(cluster_id=0, points=[])


def _map_with(cells: str, *, width: int = 3, height: int = 2) -> Map:
    return Map(header=HEADER, width=width, height=height, resolution_m=0.05,
               origin=Pose2D(x_m=0.0, y_m=0.0, theta_rad=0.0), cells=cells)


@pytest.mark.parametrize("cells, reason", [
    ("not base64!", "not base64 of a zlib stream"),
    (base64.b64encode(b"not zlib").decode(), "not base64 of a zlib stream"),
    (Map.pack_cells(bytes(5)), "5 bytes for a 3 x 2 grid (needs 6"),
    (Map.pack_cells(bytes(7)), "more than 6 bytes for a 3 x 2 grid"),
    (Map.pack_cells(bytes(6)) + Map.pack_cells(bytes(1)), "not base64"),  # padding inside: not one base64 text
    (base64.b64encode(zlib.compress(bytes(6)) + b"x").decode(), "not one whole zlib stream"),
    (base64.b64encode(zlib.compress(bytes(6))[:-2]).decode(), "not one whole zlib stream"),
    (Map.pack_cells(bytes([0, 1, 2, 3, 0, 0])), "a byte that is not 0 (free), 1 (occupied) or 2 (unknown)"),
])
def test_a_maps_cells_must_inflate_to_exactly_its_grid_of_states(cells, reason):
    with pytest.raises(ValidationError, match=re.escape(reason)):
        _map_with(cells)


def test_a_map_is_never_inflated_past_its_grid():
    # A zlib bomb: 2^24 + 1 zero bytes in 16 kB for a grid of 2^24 cells; inflating stops one byte past the grid.
    bomb = Map.pack_cells(bytes((1 << 24) + 1))
    assert len(bomb) < 40_000
    with pytest.raises(ValidationError, match="more than 16777216 bytes for a 4096 x 4096 grid"):
        _map_with(bomb, width=4096, height=4096)
    with pytest.raises(ValidationError, match="is more than the 16777216 a map may have"):
        _map_with(Map.pack_cells(bytes(1)), width=4097, height=4096)


def test_wiring_every_topic_has_one_publisher_per_run_and_a_subscriber():
    for topic in TOPICS.values():
        # A sim run's processes, or a ROS 2 robot's (the bridge in the sim's place): one publisher each.
        for source in (SIM, ROS2):
            run = {SIM.name, ROS2.name} - {source.name}
            assert len([p for p in publishers_of(topic.name) if p not in run]) <= 1
        assert publishers_of(topic.name)
        assert any(topic.name in spec.subscribes for spec in (*STAGES.values(), MONITOR))
    assert set(MONITOR.subscribes) == set(TOPICS)
    assert publishers_of("goals") == (ROS2.name,)
    assert publishers_of("map") == (ROS2.name,) and TOPICS["map"].latched
    assert set(ROS2.subscribes) == set(SIM.subscribes) and ROS2.watches == SIM.watches
    for spec in PROCESSES.values():
        for name in (*spec.publishes, *spec.subscribes):
            assert name in TOPICS


def test_wiring_keys():
    prefix = default_prefix()
    assert prefix == "cvxnav/robot1"
    assert key(prefix, "raw_path") == "cvxnav/robot1/raw_path"
    assert model_for("scan") is Scan
    assert status_key(prefix, "planner") == "cvxnav/robot1/status/planner"
    assert alive_key(prefix, "planner") == "cvxnav/robot1/alive/planner"
    with pytest.raises(KeyError):
        key(prefix, "nope")


def test_wiring_keys_parse_back_to_their_stage_and_nothing_else_does():
    prefix = default_prefix()
    for stage in ("planner", "ros2"):
        assert stage_of_status_key(prefix, status_key(prefix, stage)) == stage
        assert stage_of_alive_key(prefix, alive_key(prefix, stage)) == stage
    for foreign in (key(prefix, "scan"), status_key("cvxnav/robot2", "planner"), f"{prefix}/status/a/b",
                    f"{prefix}/status/", alive_key(prefix, "planner")):
        assert stage_of_status_key(prefix, foreign) is None


def test_export_json_schemas(tmp_path):
    paths = export_json_schemas(tmp_path)
    assert sorted(p.name for p in paths) == sorted(
        f"cvxnav.{m.__name__}.v{m.VERSION}.schema.json" for m in MESSAGE_MODELS
    )
    scan = json.loads((tmp_path / "cvxnav.Scan.v1.schema.json").read_text())
    assert scan["title"] == "cvxnav.Scan/1"
    assert scan["$id"].endswith("cvxnav.Scan/1")
    assert scan["additionalProperties"] is False
    assert set(scan["required"]) == {"header", "pose", "points"}
