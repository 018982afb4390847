"""Slinger operator console and fleet service: REST API, database, Zenoh fleet link, 3D scene.

Feature packages, each with its routes beside its service: ``accounts``, ``fleet``, ``throws``,
``console``, ``policies``, ``analysis``, ``site``, ``jobs``; ``api`` holds what the routes share,
``db`` the models. The services are built by :func:`server.services.build_services`, the app by
:func:`server.app.create_app`; nothing here does I/O at import time.
"""
