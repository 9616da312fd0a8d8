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


def test_isa_flags_reads_x86_and_arm_cpuinfo():
    from radarpc.machine import cpu_has_native_bf16, cpu_flags, isa_flags

    x86 = ("processor\t: 0\nmodel name\t: Some CPU\nflags\t\t: fpu sse4_2 avx avx2 fma f16c\n\n"
           "processor\t: 1\nflags\t\t: fpu sse4_2 avx avx2 fma f16c avx512f\n")
    assert cpu_flags(x86) == {"fpu", "sse4_2", "avx", "avx2", "fma", "f16c", "avx512f"}   # every processor's
    assert isa_flags(x86) == ["sse4_2", "avx", "avx2", "fma", "f16c", "avx512f"]        # ISA_FLAGS order
    assert isa_flags("processor\t: 0\nFeatures\t: fp asimd evtstrm sve\n") == ["asimd", "sve"]
    assert isa_flags("") == []
    assert not cpu_has_native_bf16(x86) and cpu_has_native_bf16("flags\t: avx512f amx_bf16\n")


def test_machine_record_names_the_cpu_and_threads():
    from radarpc.machine import cpu_model, isa_flags, load_average, machine_record

    rec = machine_record()
    assert rec["cpu"] == cpu_model() and rec["isa"] == isa_flags()
    assert rec["torch_threads"] == torch.get_num_threads()
    assert 1 <= rec["usable_cpus"] <= rec["logical_cpus"]
    load = load_average()
    assert load is None or (len(load) == 3 and min(load) >= 0)
