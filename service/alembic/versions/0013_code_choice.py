"""textures.code_choice: the recipe an upload's code was chosen by

Rows from before it hold NULL: their uploads' codes are the crops' mean (recipe 1), and
``texspace reencode --stale-codes`` chooses them again on models that choose by style.

Revision ID: 0013
Revises: 0012
Create Date: 2026-12-07
"""
import sqlalchemy as sa
from alembic import op

revision = "0013"
down_revision = "0012"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("textures", sa.Column("code_choice", sa.Integer(), nullable=True))


def downgrade() -> None:
    op.drop_column("textures", "code_choice")
