"""sampler_interim: a refinement's first result is served while its fit goes on

True while ``sampler_key`` names the sampler a running refinement published part way
(``TEXSPACE_FIT_INTERIM_SECONDS``); its final sampler replaces it and sets it back to false.

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-01
"""
import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("textures", sa.Column("sampler_interim", sa.Boolean(), nullable=False, server_default=sa.false()))


def downgrade() -> None:
    op.drop_column("textures", "sampler_interim")
