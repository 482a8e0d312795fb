"""textures.refinement_deferred: an upload's refinement waiting for room in the fit queue

Fits are counted apart from the other jobs, each tenant fills at most a share of each
queue. An upload whose refinement finds the fit queue (or its owner's share) full keeps
the params here and serves the encoder's code until the reaper queues it, oldest first.

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-02
"""
import sqlalchemy as sa
from alembic import op

revision = "0010"
down_revision = "0009"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("textures", sa.Column("refinement_deferred", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("textures", "refinement_deferred")
