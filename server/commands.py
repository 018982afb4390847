"""The ``slinger`` sub-commands of the server package that run a module of their own: ``worker``,
``router``, ``certs`` and ``results`` (``up``, ``server``, ``db`` and ``user`` are built into
``server.cli``).

Each function here is registered in the entry-point group ``slinger.commands`` (``pyproject.toml``,
``packaging/server/pyproject.toml``) under the sub-command's name, as the runtime's
(``runtime.commands``) and the twin's (``sim_twin.commands``) are; ``server.cli`` finds them there.
A function imports the command's module and returns it (the module has ``main(argv)``, or
``build_parser``/``run``); its docstring is the command's help line.
"""

from __future__ import annotations

from types import ModuleType


def worker() -> ModuleType:
    """a job worker: previews, evaluations, diagnoses, adaptations"""
    import server.jobs.worker as module

    return module


def router() -> ModuleType:
    """the site's Zenoh router (fleets: every process connects to it as a client)"""
    import server.site.router as module

    return module


def certs() -> ModuleType:
    """a site's CA, TLS certificates and machine command keys"""
    import server.site.certs as module

    return module


def results() -> ModuleType:
    """docs/results.md from the committed reports (--check: fail when stale)"""
    import server.site.results_page as module

    return module
