"""Database layer: SQLAlchemy 2 typed models (separate from the API schemas), engine factory,
Alembic migration helper. The schema is only ever created by Alembic (migrations/)."""
