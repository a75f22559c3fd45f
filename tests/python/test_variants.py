"""Every plugin's test file in the llvm variants.

Each ``test_fluo_<plugin>.py`` (and ``test_wrappers.py``, ``test_polarized.py``, ``test_updates.py``) parametrizes its tests by
``variant`` over ``conftest.VARIANTS``: the scalar pair in this process. Here each file runs
again in a fresh process with ``FLUO_TEST_VARIANTS=llvm_ad_spectral,llvm_ad_rgb`` (Mitsuba
3.8 cannot start an llvm variant after a scalar render), selecting the tests whose id names
an llvm variant: the same assertions against the same references (the paper's equations,
native Mitsuba, Rust's tools, analytic integrals), served by the same plugin class.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
#: Every plugin's test file (a new plugin's test_fluo_<name>.py joins by its name).
FILES = sorted(p.name for p in HERE.glob("test_fluo_*.py")) + ["test_wrappers.py", "test_polarized.py",
                                                                     "test_updates.py"]


#: The tests run: those parametrized by an llvm variant, except fluo_qd's hard cases (a
#: BSDF called point by point, each call a kernel launch: 8 minutes in llvm; the same
#: inputs render finite in test_hard_cases.py's llvm renders).
SELECT = "llvm_ad and not test06_hard_cases_are_finite"


@pytest.mark.parametrize("name", FILES)
def test01_plugin_tests_pass_in_the_llvm_variants(name):
    env = dict(os.environ, FLUO_TEST_VARIANTS="llvm_ad_spectral,llvm_ad_rgb")
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k", SELECT,
                           str(HERE / name)], capture_output=True, text=True, env=env, cwd=HERE, timeout=1800)
    tail = proc.stdout[-6000:] + proc.stderr[-2000:]
    passed = re.search(r"(\d+) passed", proc.stdout)
    print(tail[-1500:])
    assert proc.returncode == 0 and passed and int(passed.group(1)) > 0, tail
