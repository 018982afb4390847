"""``slinger train --gpus N``: the command goes through sim_twin.training.train's own main, which re-launches
itself under torchrun with one process per GPU, and refuses before anything starts when the host
has fewer GPUs than asked for. No process is started here (subprocess.call is recorded)."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from server import cli  # noqa: E402
from sim_twin.training import train  # noqa: E402


@pytest.fixture
def launches(monkeypatch) -> list[list[str]]:
    """The commands sim_twin.training.train would start, recorded instead of run."""
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    calls: list[list[str]] = []
    monkeypatch.setattr("subprocess.call", lambda cmd: calls.append(cmd) or 0)
    return calls


@pytest.mark.parametrize("gpus", [["--gpus", "4"], ["--gpus=4"]])
def test_slinger_train_with_gpus_relaunches_under_torchrun_one_process_per_gpu(monkeypatch, launches, gpus):
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 4)
    assert cli.main(["train", "--mode", "2d", *gpus, "--max-minutes", "3"]) == 0
    (cmd,) = launches
    i = cmd.index("torch.distributed.run")
    # the workers get the command as given, --gpus included, so that the model card names it
    assert cmd[i + 1:] == ["--standalone", "--nproc_per_node=4", "-m", "sim_twin.training.train", "--mode", "2d", *gpus, "--max-minutes", "3"]


def test_more_gpus_than_the_host_has_is_refused_before_anything_starts(monkeypatch, launches, capsys):
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert cli.main(["train", "--mode", "2d", "--gpus", "2"]) == 2
    assert "--gpus 2 asks for 2 CUDA GPUs; this host has 1" in capsys.readouterr().err
    assert launches == []


def test_zero_gpus_is_refused(launches, capsys):
    assert train.main(["--mode", "2d", "--gpus", "0"]) == 2
    assert "--gpus must be at least 1" in capsys.readouterr().err and launches == []


def test_a_torchrun_worker_does_not_relaunch(monkeypatch, launches):
    """Inside torchrun (WORLD_SIZE set) --gpus is not acted on again: the worker trains (here the
    run itself is replaced, so only the dispatch is checked) and knows the command for its model
    card."""
    monkeypatch.setenv("WORLD_SIZE", "2")
    ran = []
    monkeypatch.setattr(train, "run", lambda args: ran.append((args.mode, args.command)) or 0)
    assert train.main(["--mode", "3d", "--gpus", "2"]) == 0
    assert ran == [("3d", "slinger train --mode 3d --gpus 2")] and launches == []
