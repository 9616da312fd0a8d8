import sys

import numpy as np
import torch

from radarpc.machine import numeric_libraries


def test_numeric_libraries_names_the_running_versions():
    libs = numeric_libraries()
    assert libs["torch"] == torch.__version__
    assert libs["numpy"] == np.__version__
    assert libs["torch_cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert libs["numpy_blas"]


def test_numeric_libraries_without_threadpoolctl_reads_numpy_build_config(monkeypatch):
    monkeypatch.setitem(sys.modules, "threadpoolctl", None)       # import now raises ImportError
    blas = np.__config__.CONFIG["Build Dependencies"]["blas"]
    assert numeric_libraries()["numpy_blas"] == f"{blas['name']} {blas['version']}"


def test_check_device_names_what_is_wrong():
    import pytest

    from radarpc.machine import check_device

    assert check_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match="--device 'gpu' is not a torch device"):
        check_device("gpu", "--device")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device 'cuda:0': CUDA is not available.*use --device cpu"):
            check_device("cuda:0")
    else:
        n = torch.cuda.device_count()
        with pytest.raises(ValueError, match=f"only {n} CUDA device"):
            check_device(f"cuda:{n}")


def test_cpu_has_native_bf16_reads_the_flags_line():
    from radarpc.machine import cpu_has_native_bf16

    head = "processor\t: 0\nmodel name\t: AMD EPYC avx512_bf16-ready\n"   # the name is not a flag
    assert not cpu_has_native_bf16(head + "flags\t\t: fpu sse2 avx2 avx512f avx512bw\n")
    assert cpu_has_native_bf16(head + "flags\t\t: fpu avx2 avx512f avx512_bf16 avx512_vnni\n")
    assert cpu_has_native_bf16(head + "flags\t\t: fpu avx2 amx_tile amx_bf16\n")
    assert not cpu_has_native_bf16("")
