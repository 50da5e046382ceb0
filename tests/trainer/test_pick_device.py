"""`pick_device`: the device a run, a worker or an experiment's workers train on, checked where
it is named (a worker refuses a bad one at start instead of failing every run it claims)."""

from __future__ import annotations

import pytest
import torch

from trainer.utils import pick_device


def test_cpu_and_auto_name_a_device_on_any_host() -> None:
    assert pick_device("cpu") == torch.device("cpu")
    assert pick_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")


@pytest.mark.parametrize("name", ["gpu", "cpu:0", "cuda:x", "auto:1", "CUDA", ""])
def test_other_names_are_refused_with_the_valid_ones(name: str) -> None:
    with pytest.raises(ValueError, match=r"valid: auto, cpu, cuda, cuda:<index>"):
        pick_device(name)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this host has a CUDA device")
def test_cuda_without_a_cuda_device_is_refused() -> None:
    for name in ("cuda", "cuda:0"):
        with pytest.raises(ValueError, match="torch sees no CUDA device"):
            pick_device(name)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_a_cuda_index_beyond_the_hosts_devices_is_refused() -> None:
    count = torch.cuda.device_count()
    assert pick_device("cuda:0") == torch.device("cuda:0")
    with pytest.raises(ValueError, match=f"torch sees {count} CUDA device"):
        pick_device(f"cuda:{count}")
