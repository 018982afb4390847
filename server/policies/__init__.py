"""Policy versions: upload, validation, promotion and rollback, and their routes."""
