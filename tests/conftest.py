"""Shared fixtures: where the public scenarios live (the `shared/` directory next to the repository)."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    path = Path(__file__).resolve().parents[2] / "shared"
    if not path.is_dir():
        pytest.skip(f"shared directory {path} is absent (it sits next to the repository checkout)")
    return path


@pytest.fixture(scope="session")
def scenarios_dir(shared_dir: Path) -> Path:
    path = shared_dir / "scenarios"
    if not path.is_dir():
        pytest.skip(f"public scenarios directory {path} is absent")
    return path
