"""The numeric environment a study records, and what the comparison tools say about two of them."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from calibration_interfaces.provenance import (distinct_environments, environment_differences, environment_note,
                                               numeric_environment)


def test_the_environment_names_the_kernels_and_the_variables_that_choose_them(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv('OPENBLAS_CORETYPE', 'Haswell')
    monkeypatch.delenv('OPENCV_CPU_DISABLE', raising=False)
    env = numeric_environment()
    assert {'cpu', 'numpy', 'numpy_simd', 'blas', 'scipy', 'opencv', 'pybullet', 'nlopt'} <= set(env)
    assert env['OPENBLAS_CORETYPE'] == 'Haswell' and 'OPENCV_CPU_DISABLE' not in env
    # NumPy's, SciPy's and OpenCV's own OpenBLAS, each with the kernel it chose (threadpoolctl is a
    # requirement), the one the variable asked for where it was loaded after it was set.
    assert env['blas'].count('openblas') >= 2, env['blas']
    assert all(isinstance(v, str) for v in env.values())
    assert numeric_environment() == env          # the same process, the same answer (the BLAS order too)


def test_numpy_dispatch_disabled_by_its_variable_shows_in_the_environment() -> None:
    here = numeric_environment()['numpy_simd']
    if 'X86_V4' not in here:
        pytest.skip(f'this CPU has no AVX-512 dispatch to disable ({here})')
    code = 'import json; from calibration_interfaces.provenance import numeric_environment as e; print(json.dumps(e()))'
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True,
                         env={**os.environ, 'NPY_DISABLE_CPU_FEATURES': 'X86_V4 AVX512_ICL AVX512_SPR'}).stdout
    there = json.loads(out)
    assert 'X86_V4' not in there['numpy_simd'] and there['NPY_DISABLE_CPU_FEATURES'] == 'X86_V4 AVX512_ICL AVX512_SPR'
    diffs = environment_differences(numeric_environment(), there)
    assert any(d.startswith('numpy_simd: ') for d in diffs) and any('NPY_DISABLE_CPU_FEATURES: unset ->' in d
                                                                   for d in diffs), diffs


def test_differences_and_the_note_on_same_other_unknown_and_mixed_environments() -> None:
    a = {'cpu': 'x', 'blas': 'openblas SkylakeX x1'}
    b = {'cpu': 'x', 'blas': 'openblas Haswell x1', 'OPENBLAS_CORETYPE': 'Haswell'}
    assert environment_differences(a, dict(a)) == []
    assert environment_differences(a, b) == ['OPENBLAS_CORETYPE: unset -> Haswell',
                                             'blas: openblas SkylakeX x1 -> openblas Haswell x1']
    assert distinct_environments([a, None, dict(a), b, {}]) == [a, b]
    assert environment_note({'one': [], 'two': []}) == ''
    same = environment_note({'one': [a], 'two': [dict(a)]})
    assert 'two and one were made on the same numeric environment' in same
    other = environment_note({'one': [a], 'two': [b]})
    assert 'two was made on another numeric environment than one' in other and 'SkylakeX x1 -> openblas Haswell' in other
    assert 'No numeric environment recorded for old' in environment_note({'old': [], 'new': [a]})
    assert 'mixed holds runs made on 2 numeric environments' in environment_note({'mixed': [a, b], 'one': [a]})
