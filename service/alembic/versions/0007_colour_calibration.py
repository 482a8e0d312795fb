"""colour_calibration: the recipe a texture's colour tables were made by

Rows from before it hold NULL: their tables are of an unknown (older) recipe, and
``texspace recolour`` computes them again.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-28
"""
import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("textures", sa.Column("colour_calibration", sa.Integer(), nullable=True))


def downgrade() -> None:
    op.drop_column("textures", "colour_calibration")
