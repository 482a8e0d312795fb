"""textures.width_m: the photo's real width, for bakes at real size

An upload (or a PATCH) may say how wide its photo is in metres; a bake with ``unit_m``
(metres per mesh unit) then textures the mesh at that size instead of fitting the texture
to the mesh's bounds. NULL: not known.

Revision ID: 0012
Revises: 0011
Create Date: 2026-12-02
"""
import sqlalchemy as sa
from alembic import op

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("textures", sa.Column("width_m", sa.Float(), nullable=True))


def downgrade() -> None:
    op.drop_column("textures", "width_m")
