"""Running the edgecal CLI without root's permission bypass, for the tests of permission errors.

root ignores file permissions (chmod 0500 does not stop root writing, 0000 does not stop it reading),
and CI runs as root. There the CLI runs through ``setpriv`` without the two capabilities that make the
bypass (CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH): still uid 0 and the owner of the test's files, but bound
by their mode bits like any user. If that is not allowed (no CAP_SETPCAP), it runs as ``nobody``; the
test is skipped only when neither works. An unprivileged test user runs the CLI as it is.
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


def _prefixes() -> list[list[str]]:
    if os.geteuid() != 0:
        return [[]]
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root and setpriv is missing: cannot run the CLI without root's permission bypass")
    return [[setpriv, "--bounding-set=-dac_override,-dac_read_search"],
            [setpriv, f"--reuid={UNPRIVILEGED_UID}", f"--regid={UNPRIVILEGED_UID}", "--clear-groups"]]


def shared_folder() -> Path:
    """A fresh folder under /tmp that an unprivileged user can enter and write (the caller removes it)."""
    d = Path(tempfile.mkdtemp(prefix="edgecal-perm-"))
    d.chmod(0o777)
    return d


def run_cli(args: list[str], cache: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m edgecal ARGS`` bound by file permissions; skip the test if no way to run it so works.

    ``cache`` is a folder the user may write (numba's cache, when the user is not the install's owner).
    """
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache / "numba-cache"), HOME=str(cache))
    # the probe: this install imports, and a file of mode 0000 cannot be read (the bypass is really gone)
    probe_code = ("import sys, edgecal.cli\n"
                  "try:\n    open(sys.argv[1])\nexcept PermissionError:\n    sys.exit(0)\nsys.exit(3)")
    locked = cache / "probe-mode-0000"
    locked.write_text("")
    locked.chmod(0)
    failures = []
    for prefix in _prefixes():
        if prefix:
            probe = subprocess.run([*prefix, sys.executable, "-c", probe_code, str(locked)], capture_output=True,
                                   text=True, env=env, timeout=120, check=False)
            if probe.returncode != 0:
                failures.append(f"{' '.join(prefix[1:])}: {(probe.stderr.strip().splitlines() or ['exit 3'])[-1]}")
                continue
        return subprocess.run([*prefix, sys.executable, "-m", "edgecal", *args], capture_output=True, text=True,
                              env=env, timeout=timeout, cwd=str(cache), check=False)
    pytest.skip("cannot run the CLI without root's permission bypass: " + "; ".join(failures))
