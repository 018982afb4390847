"""HTTP API: one router per resource under :mod:`server.api.routes`."""
