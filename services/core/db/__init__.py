"""The platform database: SQLAlchemy 2 models, engine/session factories and Alembic migrations."""
