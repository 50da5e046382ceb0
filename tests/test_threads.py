"""The default torch thread count: the cores divided among the processes that share them."""

from __future__ import annotations

import pytest

from trainer.threads import default_threads, describe


@pytest.mark.parametrize(
    ("cores", "workers", "server", "threads"),
    [
        (2, 1, True, 1),  # `sepoa up` on a 2-core box: one thread each, not two fighting
        (2, 3, True, 1),  # more processes than cores: still at least one
        (16, 1, True, 8),
        (16, 3, True, 4),
        (16, 1, False, 16),  # a lone worker on a GPU host takes every core
    ],
)
def test_each_process_gets_its_share_of_the_cores(
    cores: int, workers: int, server: bool, threads: int
) -> None:
    assert default_threads(workers=workers, server=server, cores=cores) == threads


def test_the_choice_is_explained_at_start() -> None:
    line = describe(1, workers=1, server=True, chosen=False)
    assert line.startswith("torch threads per worker: 1 (") and "1 worker + the server" in line
    chosen = describe(3, workers=2, server=True, chosen=True)
    assert chosen == "torch threads per worker: 3 (--threads)"
