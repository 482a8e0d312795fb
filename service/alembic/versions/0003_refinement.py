"""refinement: an upload's in-place fit job and the encoder's code it replaces

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23
"""
import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("textures", sa.Column("refinement_job_id", sa.String(32), nullable=True))
    op.add_column("textures", sa.Column("encoder_code", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("textures", "encoder_code")
    op.drop_column("textures", "refinement_job_id")
