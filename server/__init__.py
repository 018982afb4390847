"""Slinger operator console and fleet service: REST API, database, Zenoh fleet link, 3D scene.

Build the app with :func:`server.app.create_app`; nothing here does I/O at import time.
"""
