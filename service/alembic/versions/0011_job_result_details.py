"""jobs.result_details: what a result file says about itself beyond its name

``{"height_range": [min, max]}``: the Rec. 709 luminance range a result's 16-bit height map
was stretched over (the same numbers as its PNG's ``texspace:height_min`` / ``_max`` text).
NULL for results without one.

Revision ID: 0011
Revises: 0010
Create Date: 2026-12-02
"""
import sqlalchemy as sa
from alembic import op

revision = "0011"
down_revision = "0010"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("jobs", sa.Column("result_details", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("jobs", "result_details")
