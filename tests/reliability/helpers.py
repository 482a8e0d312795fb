"""Plain helpers of the reliability tests (fixtures live in conftest.py): settings, the
bad-input corpus, and snapshots of what a request left behind."""
from __future__ import annotations

from pathlib import Path

from sqlalchemy import func, select

from service.context import Services
from service.settings import Settings
from service.tables import Job, Texture

BAD = Path(__file__).resolve().parents[1] / "data" / "bad"
PROBLEM = "application/problem+json"


def make_settings(root: Path, **overrides) -> Settings:
    values = dict(data_dir=root / "data", log_json=False, heartbeat_seconds=0.2, max_volume_resolution=32,
                  max_mesh_faces=1000, max_mesh_vertices=1000, auto_fit=False)
    return Settings(**(values | overrides))


def stored_files(services: Services) -> list[str]:
    """Every file in local storage (relative keys, sorted), temporary files included."""
    root = services.storage.root
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


def row_counts(services: Services) -> tuple[int, int]:
    with services.sessions() as session:
        return (session.scalar(select(func.count()).select_from(Texture)),
                session.scalar(select(func.count()).select_from(Job)))


def database_settings(database_url: str | None) -> dict:
    """Settings overrides for ``database_url`` (none for the SQLite default)."""
    return {"database_url": database_url} if database_url else {}
