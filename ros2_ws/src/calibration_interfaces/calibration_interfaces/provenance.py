"""The numeric environment a run was made in: what decides whether it repeats elsewhere.

A run of the graph is deterministic on one machine: the same seed gives the same targets, outcomes
and final error to the last digit. On another machine it need not. NumPy, OpenBLAS and OpenCV each
pick their code at run time from the CPU's instruction set (NumPy's SIMD dispatch, OpenBLAS's
``DYNAMIC_ARCH`` kernel, OpenCV's dispatch), and those kernels round differently in the last bit.
Active selection amplifies a last-bit difference: another candidate wins a selection, and from
there the run takes other poses. Measured here (AL, seeds 0 and 1 of ``make experiment``): with
NumPy's AVX-512 dispatch disabled, OpenBLAS forced to its Haswell kernel or OpenCV's AVX/AVX2
paths disabled, each run ends at another error (docs/experiment.md, "Repeating a run").

So a study records :func:`numeric_environment`, and the tools that compare two studies say when
theirs differ (:func:`environment_differences`): the runs then pair by seed (the same real robot,
guess and camera errors), but not step by step, and only the distributions are comparable.

Pure: no rclpy. NumPy and SciPy are imported, OpenCV and threadpoolctl lazily (absent: said so).
"""
from __future__ import annotations

import os
import platform
from importlib import metadata
from typing import Iterable, Mapping, Sequence

__all__ = ['ENVIRONMENT_VARIABLES', 'numeric_environment', 'environment_differences', 'distinct_environments',
           'environment_note']

#: Environment variables that change the kernels chosen (recorded when set).
ENVIRONMENT_VARIABLES = ('NPY_DISABLE_CPU_FEATURES', 'NPY_ENABLE_CPU_FEATURES', 'OPENBLAS_CORETYPE',
                         'OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'OPENCV_CPU_DISABLE')


def _cpu_model() -> str:
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as f:
            for line in f:
                if line.startswith('model name'):
                    return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(distribution: str) -> str:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return 'not installed'


def _numpy_simd() -> str:
    """The SIMD targets NumPy dispatches to on this CPU (its build's baseline first)."""
    from numpy._core._multiarray_umath import __cpu_baseline__, __cpu_dispatch__, __cpu_features__

    used = [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]
    return ' '.join(__cpu_baseline__) + (' + ' + ' '.join(used) if used else '')


def _blas() -> str:
    """Each BLAS loaded (NumPy's, SciPy's, OpenCV's): library, version, the kernel it chose, its threads."""
    import numpy  # noqa: F401  (loads its BLAS)
    import scipy.linalg  # noqa: F401  (loads SciPy's own)
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return 'unknown (threadpoolctl not installed)'
    libs = [f"{i.get('internal_api')} {i.get('version')} {i.get('architecture', '?')} x{i.get('num_threads')}"
            for i in threadpool_info() if i.get('user_api') == 'blas']
    return '; '.join(sorted(libs)) or 'none found'      # sorted: the load order varies


def _opencv() -> str:
    try:
        import cv2
    except ImportError:
        return 'not installed'
    # '*' marks the dispatched features, '?' those disabled (OPENCV_CPU_DISABLE).
    return f'{cv2.__version__} ({cv2.getCPUFeaturesLine()})'


def numeric_environment() -> dict[str, str]:
    """What decides whether a run made here repeats on another machine, as printable strings.

    Returns
    -------
    dict
        ``cpu`` (model name), ``machine``, ``python``, ``numpy`` (version), ``numpy_simd``
        (baseline + the dispatch targets in use), ``blas`` (each loaded BLAS: library, version,
        kernel, threads), ``scipy``, ``opencv`` (version and its dispatched CPU features),
        ``pybullet``, ``nlopt``, and each variable of :data:`ENVIRONMENT_VARIABLES` that is set.
    """
    import numpy
    import scipy

    opencv = _opencv()       # first: OpenCV loads a BLAS of its own, which the list must hold every time
    env = {'cpu': _cpu_model(), 'machine': platform.machine(), 'python': platform.python_version(),
           'numpy': numpy.__version__, 'numpy_simd': _numpy_simd(), 'blas': _blas(), 'scipy': scipy.__version__,
           'opencv': opencv, 'pybullet': _version('pybullet'), 'nlopt': _version('nlopt')}
    env.update({k: os.environ[k] for k in ENVIRONMENT_VARIABLES if k in os.environ})
    return env


def environment_differences(first: Mapping[str, str], second: Mapping[str, str]) -> list[str]:
    """``'key: first -> second'`` for every entry that differs (a missing one shows as ``unset``)."""
    return [f"{k}: {first.get(k, 'unset')} -> {second.get(k, 'unset')}"
            for k in sorted(set(first) | set(second)) if first.get(k) != second.get(k)]


def distinct_environments(environments: Iterable[Mapping[str, str] | None]) -> list[dict[str, str]]:
    """The distinct environments among ``environments`` (in first-seen order; None entries dropped)."""
    out: list[dict[str, str]] = []
    for env in environments:
        if env and dict(env) not in out:
            out.append(dict(env))
    return out


def environment_note(studies: Mapping[str, Sequence[Mapping[str, str]]]) -> str:
    """One paragraph for a comparison of studies: whether their runs can repeat one another.

    Parameters
    ----------
    studies : mapping
        Study name -> the distinct :func:`numeric_environment` records of its runs (empty where
        none was recorded: made before studies recorded it, or a committed summary). The first
        study is the baseline.

    Returns
    -------
    str
        Empty when no study recorded one.
    """
    names = list(studies)
    if not any(studies.values()):
        return ''
    parts = []
    unknown = [n for n in names if not studies[n]]
    if unknown:
        parts.append(f"No numeric environment recorded for {', '.join(unknown)}: whether its runs can repeat "
                     'those of the same seed in the others is not known.')
    mixed = [n for n in names if len(studies[n]) > 1]
    for name in mixed:
        parts.append(f'{name} holds runs made on {len(studies[name])} numeric environments '
                     f'({"; ".join(environment_differences(studies[name][0], studies[name][1]))}).')
    single = [n for n in names if len(studies[n]) == 1]
    if len(single) > 1:
        base = single[0]
        for name in single[1:]:
            diffs = environment_differences(studies[base][0], studies[name][0])
            if diffs:
                parts.append(f'{name} was made on another numeric environment than {base} ({"; ".join(diffs)}): '
                             'runs of the same seed share their robot, guess and errors but are not expected '
                             'to repeat one another step by step; compare the distributions.')
            else:
                parts.append(f'{name} and {base} were made on the same numeric environment: what differs '
                             'between their runs comes from their settings or code, not from the machine.')
    return ' '.join(parts)
