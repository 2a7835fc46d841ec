"""Running the edgecal CLI as an unprivileged user, for the tests of permission errors.

root ignores file permissions (chmod 0500 does not stop root writing, 0000 does not stop it reading),
and CI runs as root: there the CLI is run as ``nobody`` through ``setpriv``. Elsewhere the test user is
unprivileged already and the CLI runs as it is.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

UNPRIVILEGED_UID = 65534  # nobody / nogroup on Debian


def _command_prefix() -> list[str]:
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root and setpriv is missing: cannot run the CLI without root's permission bypass")
    return [setpriv, f"--reuid={UNPRIVILEGED_UID}", f"--regid={UNPRIVILEGED_UID}", "--clear-groups"]


def shared_folder() -> Path:
    """A fresh folder under /tmp that the unprivileged user can enter and write (the caller removes it)."""
    d = Path(tempfile.mkdtemp(prefix="edgecal-perm-"))
    d.chmod(0o777)
    return d


def run_cli(args: list[str], cache: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m edgecal ARGS`` as an unprivileged user; skip the test if that user cannot run this install.

    ``cache`` is a folder the user may write (numba's cache: the install's own __pycache__ is root's).
    """
    prefix = _command_prefix()
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache / "numba-cache"), HOME=str(cache))
    if prefix:
        probe = subprocess.run([*prefix, sys.executable, "-c", "import edgecal.cli"], capture_output=True, text=True,
                               env=env, timeout=120)
        if probe.returncode != 0:
            pytest.skip("the unprivileged user cannot import this edgecal install (is it under a private home "
                        f"folder?): {probe.stderr.strip().splitlines()[-1:] or probe.returncode}")
    return subprocess.run([*prefix, sys.executable, "-m", "edgecal", *args], capture_output=True, text=True,
                          env=env, timeout=timeout, cwd=str(cache))
