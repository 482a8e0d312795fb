"""Alembic environment: runs migrations online against the configured URL.

On PostgreSQL a transaction-level advisory lock serialises concurrent starts of
several API / worker processes.
"""
from alembic import context
from sqlalchemy import create_engine, pool, text

from service.tables import Base

config = context.config
target_metadata = Base.metadata
MIGRATION_LOCK_ID = 7_301_551  # arbitrary, constant: "texspace migrations"


def run_migrations_online() -> None:
    url = config.get_main_option("sqlalchemy.url")
    engine = create_engine(url, poolclass=pool.NullPool)
    with engine.connect() as connection:
        context.configure(
            connection=connection,
            target_metadata=target_metadata,
            render_as_batch=connection.dialect.name == "sqlite",
        )
        with context.begin_transaction():
            if connection.dialect.name == "postgresql":
                connection.execute(text(f"SELECT pg_advisory_xact_lock({MIGRATION_LOCK_ID})"))
            context.run_migrations()


run_migrations_online()
