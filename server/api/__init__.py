"""What every feature's routes share: the typed dependencies (``deps``), the one mapping of domain errors to
HTTP answers (``errors``, ``responses``), the shared schemas and the HTTP hygiene middlewares (``web_guard``).
Each feature package keeps its own routes beside its service (``server/<feature>/*routes.py``)."""
