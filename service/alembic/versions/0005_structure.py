"""structure: what a fit found in the photo and built in (grain axis, repeat lattice)

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-25
"""
import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("textures", sa.Column("structure", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("textures", "structure")
