"""lighting: whether a texture's photo is encoded and fitted with its shading evened out

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-27
"""
import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("textures", sa.Column("lighting", sa.String(8), nullable=False, server_default="as-is"))


def downgrade() -> None:
    op.drop_column("textures", "lighting")
