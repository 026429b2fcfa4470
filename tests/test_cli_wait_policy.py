"""The ``unibody`` command waits passively in OpenMP barriers (benchmarks/cli_contention.py), the library does not."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = (
    "import sys; sys.argv[0] = {argv0!r}; import unibody, os, torch; "
    "print(repr(os.environ.get('OMP_WAIT_POLICY')))"
)


@pytest.mark.parametrize(
    ("argv0", "given", "expected"),
    [
        ("/venv/bin/unibody", None, "'PASSIVE'"),  # the command
        ("/venv/bin/unibody", "ACTIVE", "'ACTIVE'"),  # never over the user's setting
        ("/venv/bin/unibody", "", "''"),  # empty: libgomp's default
        ("-c", None, "None"),  # a program importing the library
        ("/home/me/train.py", None, "None"),
    ],
)
def test_wait_policy(argv0, given, expected):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    out = subprocess.run(
        [sys.executable, "-c", PROBE.format(argv0=argv0)], env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip().splitlines()[-1] == expected
