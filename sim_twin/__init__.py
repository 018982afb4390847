"""Digital twin, simulated machine, training and diagnosis of the Slinger throwing system.

Packages: ``twin`` (the MuJoCo model, hydraulics, reality profiles and effects, the simulated machine),
``training``, ``evaluation``, ``preview``, ``adaptation`` and ``diagnosis``; ``commands`` holds the
package's ``slinger`` sub-commands. Who may import whom: pyproject.toml's import-linter contracts.
"""

from pathlib import Path

POLICY_DIR = Path(__file__).resolve().parent.parent / "policies"
"""The repository's committed policies (throw2d.onnx, throw3d.onnx): the default of every command
that takes ``--policy``, so that a command run outside the repository root still finds them."""


def default_policy(mode: str) -> Path:
    """The committed policy of ``mode`` ('2d' or '3d'): ``policies/throw<mode>.onnx`` in the repository.
    Raises ValueError for another mode."""
    if mode not in ("2d", "3d"):
        raise ValueError(f"mode must be '2d' or '3d', got {mode!r}")
    return POLICY_DIR / f"throw{mode}.onnx"
