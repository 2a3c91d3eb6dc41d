"""The processor code paths of the numerical libraries, pinned so that two machines compute the same bytes.

NumPy, OpenBLAS (inside NumPy and SciPy) and OpenCV choose their kernels at run time from the processor's
instruction set: on a processor with AVX-512 they run other kernels than on one with AVX2 only, and other
kernels round differently (another summation order in a matrix product, another approximation of a
transcendental function). One such rounding difference in the stereo visual odometry grows into
centimetres of ground truth, and every number downstream of it differs (measured 2026-11-25: the same
`tile_ld_00` bag gave trajectories 8 cm apart with OpenCV's AVX2 kernels disabled and 5 cm apart with
OpenBLAS's Sandy Bridge kernels instead of its Haswell ones; a machine with AVX-512 gave other ground truth
for every sequence of `mini` from byte-identical bags).

:func:`pin` caps all three at the x86-64-v3 level (AVX2 + FMA) on a processor that has it, the level
every machine of the kind the benchmark is run on has, by their own documented switches, which must be set
before the library loads:

- ``NPY_DISABLE_CPU_FEATURES``: NumPy's AVX-512 dispatch targets off;
- ``OPENBLAS_CORETYPE=Haswell``: OpenBLAS's AVX2 kernels, whatever processor it detects;
- ``OPENCV_CPU_DISABLE``: OpenCV's AVX-512 dispatch targets off (only those this processor has: OpenCV
  prints a line for each unavailable one).

Numba compiles for the host processor but without ``fastmath`` LLVM keeps IEEE semantics (no reassociated
sums, no approximate functions): its results do not depend on the vector width, so it is left native and
only recorded (:func:`code_paths`).

It runs when ``skidbench.pipeline`` is imported (the ``skidbench`` command and every subpackage import it
first), so it is in place before NumPy loads in a skidbench process and in every worker process it starts
(they inherit the environment). A variable the user set is kept; ``SKIDBENCH_NATIVE_CPU=1`` keeps every
library's native choice (faster on some processors; results then may differ between machines). A process
that imported NumPy before skidbench keeps NumPy's and OpenBLAS's native paths: :func:`code_paths` says
which paths a process really runs, and every MLflow run records it.
"""

from __future__ import annotations

import os
from functools import lru_cache

#: set to 1 to keep each library's native processor code paths (not reproducible across machines)
NATIVE_ENV = "SKIDBENCH_NATIVE_CPU"
#: the x86-64-v3 flags (Linux ``/proc/cpuinfo`` names) the pinned paths need
V3_FLAGS = ("avx", "avx2", "fma", "f16c", "bmi1", "bmi2")
#: OpenCV's AVX-512 feature names (``OPENCV_CPU_DISABLE``) and the cpuinfo flags each needs
OPENCV_AVX512 = {
    "AVX512F": ("avx512f",),
    "AVX512-COMMON": ("avx512f", "avx512cd"),
    "AVX512-SKX": ("avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl"),
    "AVX512-CLX": ("avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl", "avx512_vnni"),
    "AVX512-CNL": ("avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl", "avx512ifma", "avx512vbmi"),
    "AVX512-ICL": (
        "avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl", "avx512ifma", "avx512vbmi",
        "avx512_vbmi2", "avx512_bitalg", "avx512_vpopcntdq", "avx512_vnni",
    ),
}  # fmt: skip
#: NumPy's names of its dispatch targets above x86-64-v3 (2.4 groups them by x86-64 level; before, by
#: feature). A name a NumPy version does not know is ignored by it with an ImportWarning.
NUMPY_AVX512 = {
    "new": "X86_V4 AVX512_ICL AVX512_SPR",
    "old": "AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR",
}


@lru_cache(maxsize=1)
def cpu_flags() -> frozenset[str]:
    """The processor's feature flags (Linux ``/proc/cpuinfo``; empty elsewhere)."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("flags"):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


@lru_cache(maxsize=1)
def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or platform.machine() or "unknown"


def _numpy_naming() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        major, minor = (int(x) for x in version("numpy").split(".")[:2])
    except (PackageNotFoundError, ValueError):
        return "new"
    return "new" if (major, minor) >= (2, 4) else "old"


def pins(flags: frozenset[str] | None = None) -> dict[str, str]:
    """The environment variables that cap the libraries at x86-64-v3 on a processor with ``flags``
    (empty on a processor without AVX2 + FMA, or not x86: there is nothing to cap to)."""
    flags = cpu_flags() if flags is None else flags
    if not all(f in flags for f in V3_FLAGS):
        return {}
    out = {"OPENBLAS_CORETYPE": "Haswell"}
    if "avx512f" in flags:
        out["NPY_DISABLE_CPU_FEATURES"] = NUMPY_AVX512[_numpy_naming()]
        ocv = [name for name, need in OPENCV_AVX512.items() if all(f in flags for f in need)]
        out["OPENCV_CPU_DISABLE"] = ",".join(ocv)
    return out


def pin() -> dict[str, str]:
    """Sets the :func:`pins` variables that are not set yet (unless ``SKIDBENCH_NATIVE_CPU=1``); returns
    those it set."""
    if os.environ.get(NATIVE_ENV, "").strip() not in ("", "0"):
        return {}
    done = {}
    for key, value in pins().items():
        if key not in os.environ:
            os.environ[key] = value
            done[key] = value
    return done


def code_paths() -> dict[str, str]:
    """The code paths this process runs: NumPy's highest active dispatch target, OpenBLAS's kernel and
    threads, OpenCV's highest enabled target, Numba's target processor, and whether they are pinned.
    Loads NumPy and OpenCV (once per process: a tenth of a second)."""
    import numpy as np

    out: dict[str, str] = {"pinned": "no" if os.environ.get(NATIVE_ENV, "") not in ("", "0") else "yes"}
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:  # NumPy < 2
        from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    active = [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]
    out["numpy"] = active[-1] if active else "baseline"
    out["openblas"] = _openblas(np)
    try:
        import cv2

        out["opencv"] = _opencv(cv2)
    except ImportError:
        pass
    try:
        import llvmlite.binding as ll

        out["numba"] = os.environ.get("NUMBA_CPU_NAME") or ll.get_host_cpu_name()
    except ImportError:
        pass
    if out["pinned"] == "yes" and not all(os.environ.get(k) == v for k, v in pins().items()):
        out["pinned"] = "partly (set before skidbench, or by the user)"
    return out


def _openblas(np) -> str:
    try:
        from threadpoolctl import threadpool_info

        libs = [i for i in threadpool_info() if i.get("internal_api") == "openblas"]
        if libs:
            return ", ".join(sorted({f"{i.get('architecture')} x{i.get('num_threads')}" for i in libs}))
    except Exception:  # noqa: BLE001 - a report, never a failure
        pass
    return os.environ.get("OPENBLAS_CORETYPE", "unknown")


def _opencv(cv2) -> str:
    names = ["AVX512_SKX", "AVX2", "AVX", "SSE4_2", "SSE4_1"]
    ids = {"AVX512_SKX": 256, "AVX2": 11, "AVX": 10, "SSE4_2": 7, "SSE4_1": 6}  # cv::CpuFeatures
    for n in names:
        try:
            if cv2.checkHardwareSupport(ids[n]):
                return n
        except Exception:  # noqa: BLE001
            break
    return "baseline"
