import sys

import numpy as np
import torch

from radarpc.machine import cpu_model, numeric_libraries


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


def test_cpu_model_is_a_non_empty_string():
    assert isinstance(cpu_model(), str) and cpu_model()
