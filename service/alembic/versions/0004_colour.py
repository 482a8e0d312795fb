"""colour: each texture's colour table, and the one of its encoder code

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-23
"""
import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("textures", sa.Column("colour", sa.JSON(), nullable=True))
    op.add_column("textures", sa.Column("encoder_colour", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("textures", "encoder_colour")
    op.drop_column("textures", "colour")
