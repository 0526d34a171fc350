"""The MuJoCo releases that generation supports, and the release that rendered a split.

Generation is tested with MuJoCo :data:`MUJOCO_MIN_VERSION` up to, not including,
:data:`MUJOCO_BELOW_VERSION`: pyproject.toml declares the same range
(:data:`MUJOCO_REQUIREMENT`; tests/core/test_mujoco_version.py checks that they agree).  Older
releases cannot build the scenes: 3.3 and 3.4 refuse the integer light type that
``MjSpec.add_light`` is given and do not render the point light of ``--rgb``.  What is identical
between releases of the range is stated in docs/generation.md (Reproducibility).

Nothing here imports MuJoCo: the installed version is read from the distribution's metadata,
so ``verify`` and ``info`` can compare it with a split's without a GL library.
"""

from __future__ import annotations

import functools
import re
import sys
from importlib.metadata import PackageNotFoundError, version

from articulated_dataset.core.errors import DataFormatError, RenderError

#: Oldest supported MuJoCo release (major, minor).
MUJOCO_MIN_VERSION = (3, 5)
#: First MuJoCo release (major, minor) that is not supported (not tested).
MUJOCO_BELOW_VERSION = (4, 1)
#: The supported range as pyproject.toml's requirement.
MUJOCO_REQUIREMENT = "mujoco>={}.{},<{}.{}".format(*MUJOCO_MIN_VERSION, *MUJOCO_BELOW_VERSION)
#: Manifest key of generated splits: the MuJoCo release that rendered them.
MANIFEST_KEY = "mujoco_version"

#: A release's leading ``major.minor``.
_RELEASE = re.compile(r"([0-9]+)\.([0-9]+)")
#: What a recorded version may look like (PEP 440 characters; never control characters).
_VERSION_TEXT = re.compile(r"[0-9A-Za-z.+!_-]{1,64}")


@functools.lru_cache(maxsize=1)
def _distribution_version() -> str | None:
    try:
        return version("mujoco")
    except PackageNotFoundError:
        return None


def installed_mujoco_version() -> str | None:
    """The installed MuJoCo's version (its distribution's metadata, else the imported module's
    ``__version__``), or None where MuJoCo is not installed."""
    found = _distribution_version()
    if found is None and "mujoco" in sys.modules:
        found = getattr(sys.modules["mujoco"], "__version__", None)
    return found


def unsupported_mujoco(found: str | None) -> str | None:
    """One line saying that MuJoCo ``found`` is outside the supported range, or None where it is
    inside it (or is None: no MuJoCo, which the commands that import it report themselves)."""
    if found is None:
        return None
    m = _RELEASE.match(found)
    if m is not None and MUJOCO_MIN_VERSION <= (int(m.group(1)), int(m.group(2))) < MUJOCO_BELOW_VERSION:
        return None
    spec = MUJOCO_REQUIREMENT.removeprefix("mujoco")
    return (f"MuJoCo {found[:40]} is installed; artdata supports MuJoCo {spec} "
            f"(pip install '{MUJOCO_REQUIREMENT}')")


def check_supported_mujoco() -> None:
    """Raise :class:`RenderError` (one line naming the supported range) where the installed
    MuJoCo is outside it."""
    problem = unsupported_mujoco(installed_mujoco_version())
    if problem is not None:
        raise RenderError(problem)


def recorded_mujoco_version(manifest: dict, where: str) -> str | None:
    """The MuJoCo release a split's manifest records (None: not recorded, e.g. a real-capture
    split); a value that is no version string is a :class:`DataFormatError` naming ``where``."""
    recorded = manifest.get(MANIFEST_KEY)
    if recorded is None:
        return None
    if not isinstance(recorded, str) or _VERSION_TEXT.fullmatch(recorded) is None:
        raise DataFormatError(f"{where}: corrupt manifest ({MANIFEST_KEY} is not a version: {ascii(recorded)[:40]})")
    return recorded


def manifest_entry() -> dict:
    """``{"mujoco_version": <installed release>}``, the key a generated split's manifest records
    (empty where no MuJoCo is installed)."""
    found = installed_mujoco_version()
    return {} if found is None else {MANIFEST_KEY: found}


def different_mujoco(manifest: dict, where: str) -> str | None:
    """``rendered with MuJoCo 3.8.1 (this machine has 4.0.1)`` where the split's recorded
    release is not the installed one; None where they agree or either is unknown."""
    recorded, found = recorded_mujoco_version(manifest, where), installed_mujoco_version()
    if recorded is None or found is None or recorded == found:
        return None
    return f"rendered with MuJoCo {recorded} (this machine has {found[:40]})"
