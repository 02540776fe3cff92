"""What a result was computed on, for provenance records.

A training run repeats to the digit only on the same arithmetic: the same library versions and the
same SIMD kernels. numpy and torch pick their kernels at import from the CPU (on an AVX-512 machine
``np.exp`` and OpenBLAS matmul give other bits than on an AVX2 one; docs/results.md), unless
environment variables cap them. So every provenance record carries the CPU, the kernels the
libraries dispatched, their versions and those variables, and a resumed run says when it continues
on different arithmetic.
"""

from __future__ import annotations

import functools
import os
import platform
import sys
from importlib import metadata

# Variables that change which kernels run, or how many threads split a reduction.
ARITHMETIC_ENV = ("ATEN_CPU_CAPABILITY", "MKL_CBWR", "DNNL_MAX_CPU_ISA", "NPY_DISABLE_CPU_FEATURES",
                  "NPY_ENABLE_CPU_FEATURES", "OPENBLAS_CORETYPE", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                  "OPENBLAS_NUM_THREADS", "CUBLAS_WORKSPACE_CONFIG")
PACKAGES = ("torch", "numpy", "mujoco", "h5py")
# The fields whose difference means "not the same arithmetic" (the rest describe, e.g. the host name).
ARITHMETIC_KEYS = ("cpu", "torch_cpu_capability", "numpy_simd", "packages", "env", "torch_threads")


def _cpu() -> str:
    """Vendor model name plus family/model/stepping (cloud CPUs often report only 'AMD EPYC')."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break  # the first processor's block is enough
                k, _, v = line.partition(":")
                fields[k.strip()] = v.strip()
    except OSError:
        return platform.processor() or platform.machine()
    name = fields.get("model name", platform.machine())
    ids = [f"{label} {fields[k]}" for k, label in (("cpu family", "family"), ("model", "model"),
                                                   ("stepping", "stepping")) if k in fields]
    return f"{name} ({', '.join(ids)})" if ids else name


def _numpy_simd() -> list[str]:
    """The SIMD targets numpy dispatches to here: compiled in, supported by the CPU, not disabled."""
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:  # numpy < 2
        from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    return [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]


def _version(pkg: str) -> str | None:
    try:
        return metadata.version(pkg)
    except metadata.PackageNotFoundError:
        return None


@functools.lru_cache(maxsize=1)
def _static() -> dict:
    return {"cpu": _cpu(), "cores": os.cpu_count(), "os": platform.platform(),
            "python": platform.python_version(), "numpy_simd": _numpy_simd(),
            "packages": {p: v for p in PACKAGES if (v := _version(p))}}


def machine_record() -> dict:
    """This process's machine: CPU, dispatched kernels, package versions and the variables above
    that are set. torch's kernel level and its intra-op thread count are read only when torch is
    already imported (a record never costs a torch import); the threads are the values that change
    while a process runs, and a reduction split over another number of threads adds in another order."""
    rec = dict(_static())
    torch = sys.modules.get("torch")
    if torch is not None:
        rec["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
        rec["torch_threads"] = torch.get_num_threads()
    rec["env"] = {k: os.environ[k] for k in ARITHMETIC_ENV if k in os.environ}
    return rec


def arithmetic_differences(before: dict | None, now: dict | None = None) -> list[str]:
    """``key: before -> now`` for each arithmetic field that differs; empty when ``before`` is
    unknown (a record from a motok that did not write one)."""
    if not before:
        return []
    now = machine_record() if now is None else now
    return [f"{k}: {before.get(k)} -> {now.get(k)}" for k in ARITHMETIC_KEYS
            if k in before and k in now and before[k] != now[k]]
