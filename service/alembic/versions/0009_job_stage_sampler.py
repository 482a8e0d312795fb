"""jobs.stage and jobs.sampler: fits that pause after their interim; what each job sampled with

``stage`` is ``"interim"`` while an upload's fit waits, paused after its interim, for its
continuation (its training state stored under the job's ``paused/`` key); NULL otherwise.
Fits that have not reached their interim run first.

``sampler`` is what a job synthesised with: ``{"kind": "encoder" | "interim" | "fitted",
"version", "key"}`` (a volume, bake or region made while its texture was refining says so).

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-02
"""
import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("jobs", sa.Column("stage", sa.String(16), nullable=True))
    op.add_column("jobs", sa.Column("sampler", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("jobs", "sampler")
    op.drop_column("jobs", "stage")
