"""`tests/benchmarks/device_runs.sh state RUN_DIR NAME` packs what resuming a run needs into
runs/state/NAME.tar (gzip), laid out as `device_runs.sh start NAME` unpacks it, and nothing else;
a directory without a checkpoint is refused and writes nothing; `collect` brings back what resuming
needs, in each run's own tar too (a state.tar over a device call's 16 MiB file limit is left out);
`after PREV NAME ...` starts NAME only once PREV has stopped, also where PREV is itself queued by an
`after` (runs in turn on one GPU)."""

import subprocess
import tarfile
import time
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "tests" / "benchmarks" / "device_runs.sh"


def _state(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), "state", *args], cwd=cwd, capture_output=True, text=True, timeout=60)


def test_state_keeps_what_resuming_needs_under_the_run_name(tmp_path):
    src = tmp_path / "policies" / "training" / "throw2d-old"
    for rel in ["checkpoint.pt", "config.json", "curve.csv", "matrices/matrix_gate.json", "tb/events.1",
                "candidates/checkpoint_25.pt", "README.md"]:
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text(rel)
    r = _state(tmp_path, str(src) + "/", "throw2d-new")
    assert r.returncode == 0, r.stderr
    tar = tmp_path / "runs" / "state" / "throw2d-new.tar"
    with tarfile.open(tar) as t:  # gzip, read as `tar xf` reads it
        files = sorted(m.name for m in t.getmembers() if m.isfile())
        assert t.extractfile("runs/throw2d-new/checkpoint.pt").read() == b"checkpoint.pt"
    assert files == ["runs/throw2d-new/checkpoint.pt", "runs/throw2d-new/config.json", "runs/throw2d-new/curve.csv",
                     "runs/throw2d-new/matrices/matrix_gate.json"]
    out = tmp_path / "unpacked"
    out.mkdir()
    subprocess.run(["tar", "xf", str(tar)], cwd=out, check=True)
    assert (out / "runs" / "throw2d-new" / "config.json").read_text() == "config.json"


def test_state_refuses_a_directory_without_a_checkpoint(tmp_path):
    src = tmp_path / "run"
    src.mkdir()
    (src / "config.json").write_text("{}")
    r = _state(tmp_path, str(src), "x")
    assert r.returncode == 1
    assert "has no checkpoint.pt" in r.stderr
    assert not (tmp_path / "runs" / "state" / "x.tar").exists()


def _collect(work: Path, out: Path) -> subprocess.CompletedProcess:
    env = {"PATH": "/usr/bin:/bin", "SLINGER_RUNS_WORK": str(work), "OUT": str(out)}
    return subprocess.run(["bash", str(SCRIPT), "collect"], env=env, capture_output=True, text=True, timeout=120)


def _run_dir(work: Path, name: str, card_iteration: int | None) -> None:
    run = work / "runs" / name
    for rel in ["checkpoint.pt", "curve.csv", "train.log", "candidates/checkpoint_25.pt", "candidates/checkpoint_50.pt",
                "candidates/checkpoint_50.onnx"]:
        (run / rel).parent.mkdir(parents=True, exist_ok=True)
        (run / rel).write_text(rel)
    if card_iteration is not None:
        (run / "throw2d.card.json").write_text(f'{{"iteration": {card_iteration}}}')


def test_collect_leaves_candidate_checkpoints_behind_but_the_exported_ones(tmp_path):
    work, out = tmp_path / "work", tmp_path / "out"
    out.mkdir()
    _run_dir(work, "passed", card_iteration=50)
    _run_dir(work, "running", card_iteration=None)
    r = _collect(work, out)
    assert r.returncode == 0, r.stderr
    for name, kept_pt in [("passed", ["runs/passed/candidates/checkpoint_50.pt"]), ("running", [])]:
        with tarfile.open(out / f"{name}.tar") as t:
            files = {m.name for m in t.getmembers() if m.isfile()}
        assert sorted(f for f in files if f.startswith(f"runs/{name}/candidates/") and f.endswith(".pt")) == kept_pt
        assert f"runs/{name}/candidates/checkpoint_50.onnx" in files and f"runs/{name}/train.log" not in files
        assert f"runs/{name}/logs/machine1.log.gz" in files  # in the tar: a call brings back a limited number of files
    assert sorted(p.name for p in out.iterdir() if p.name.endswith(".gz")) == []


def test_collect_brings_back_the_state_that_resumes_each_run_in_one_file(tmp_path):
    work, out = tmp_path / "work", tmp_path / "out"
    out.mkdir()
    _run_dir(work, "resumable", card_iteration=None)
    (work / "runs" / "resumable" / "config.json").write_text("{}")
    (work / "runs" / "resumable" / "matrices").mkdir()
    (work / "runs" / "resumable" / "matrices" / "site_matrix_2d_it25.png").write_text("plot")
    (work / "runs" / "resumable" / "matrices" / "site_matrix_2d_it25.json").write_text("{}")
    _run_dir(work, "no-config", card_iteration=None)  # not resumable: no state for it
    r = _collect(work, out)
    assert r.returncode == 0, r.stderr
    here = tmp_path / "here"
    here.mkdir()
    subprocess.run(["tar", "xf", str(out / "state.tar")], cwd=here, check=True)
    assert sorted(p.name for p in (here / "runs" / "state").iterdir()) == ["resumable.tar"]
    with tarfile.open(here / "runs" / "state" / "resumable.tar") as t:
        files = sorted(m.name for m in t.getmembers() if m.isfile())
    assert files == ["runs/resumable/checkpoint.pt", "runs/resumable/config.json", "runs/resumable/curve.csv",
                     "runs/resumable/logs/machine1.log.gz", "runs/resumable/matrices/site_matrix_2d_it25.json"]
    assert not (work / ".state").exists()


def _fake_runs(tmp_path: Path):
    """`start` runs `python3 -m sim_twin.training.train ...`: a stand-in python3 on PATH records when
    each run starts and ends (2 s), so the order is checked without training anything. Returns the
    work directory and a function running the script there."""
    work, fake = tmp_path / "work", tmp_path / "bin"
    (work / "tests" / "benchmarks").mkdir(parents=True)
    (work / "tests" / "benchmarks" / "device_runs.sh").write_text(SCRIPT.read_text())
    fake.mkdir()
    (fake / "python3").write_text('#!/bin/bash\necho "start $(date +%s.%N) $*"\nsleep 2\necho "end $(date +%s.%N)"\n')
    (fake / "python3").chmod(0o755)
    env = {"PATH": f"{fake}:/usr/bin:/bin", "SLINGER_RUNS_WORK": str(work)}

    def sh(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(SCRIPT), *args], env=env, capture_output=True, text=True, timeout=60)

    return work, sh


def _times(log: Path, deadline_s: float = 40) -> dict[str, float]:
    """{"start": t, "end": t} of a stand-in run's log, once it has ended (within ``deadline_s``)."""
    deadline = time.time() + deadline_s
    while time.time() < deadline and "end" not in (log.read_text() if log.exists() else ""):
        time.sleep(0.5)
    return {k: float(v.split()[0]) for k, v in (line.split(" ", 1) for line in log.read_text().splitlines())}


def test_after_starts_the_next_run_once_the_previous_one_has_stopped(tmp_path):
    work, sh = _fake_runs(tmp_path)
    assert sh("start", "first", "2d", "cfg.json", "2", "--seed", "21").returncode == 0
    r = sh("after", "first", "second", "2d", "cfg.json", "2", "--seed", "23", "--note", "two words")
    assert r.returncode == 0 and "second starts once first has stopped" in r.stdout, r.stderr
    log = work / "runs" / "second" / "train.log"
    deadline = time.time() + 30
    while time.time() < deadline and "end" not in (log.read_text() if log.exists() else ""):
        time.sleep(0.5)
    first = dict(line.split(" ", 1) for line in (work / "runs" / "first" / "train.log").read_text().splitlines())
    second = (log.read_text()).splitlines()
    assert float(second[0].split()[1]) >= float(first["end"]), "the second run started before the first had stopped"
    assert second[0].split(" ", 2)[2] == ("-m sim_twin.training.train --mode 2d --config cfg.json --log-dir runs/second "
                                          "--gate-workers 2 --max-minutes 600 --seed 23 --note two words")
    assert not subprocess.run(["pgrep", "-f", "slinger-[a]fter"], capture_output=True).stdout  # the waiter is gone


def test_after_a_queued_run_waits_for_it_too(tmp_path):
    """Three runs in turn on one GPU, both `after`s issued at once: the third waits for the second, which
    is still queued behind the first when the third's waiter starts (it once found no `second` training
    and started at once, two runs sharing the GPU)."""
    work, sh = _fake_runs(tmp_path)
    assert sh("start", "first", "2d", "cfg.json", "2").returncode == 0
    assert sh("after", "first", "second", "2d", "cfg.json", "2").returncode == 0
    assert sh("after", "second", "third", "2d", "cfg.json", "2").returncode == 0
    third = _times(work / "runs" / "third" / "train.log")
    first, second = (_times(work / "runs" / n / "train.log", 1) for n in ("first", "second"))
    assert first["end"] <= second["start"] and second["end"] <= third["start"], (first, second, third)


def _run_with_pending(tmp_path: Path, candidate_files: list[str]) -> Path:
    """A run directory whose gate had iteration 575 under test at seed index 1 (``candidate_files``: the
    files under ``candidates/`` besides iteration 550's, which no state carries)."""
    import json

    src = tmp_path / "runs" / "throw2d-x"
    for rel in ["checkpoint.pt", "config.json", "accelerators.json", "logs/machine1.log.gz",
                "candidates/checkpoint_550.onnx", "candidates/checkpoint_550.json", *candidate_files]:
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text(rel)
    (src / "matrices").mkdir()
    (src / "matrices" / "matrix_gate.json").write_text(json.dumps({"results": [], "pending": {
        "iteration": 575, "onnx": "runs/throw2d-x/candidates/checkpoint_575.onnx", "train_wall_s": 646.0, "seed_index": 1}}))
    return src


def _passing_gate(out_dir: Path):
    """A MatrixGate on ``out_dir`` whose site matrix is a one-cell report that meets its bar (the
    files the resumed gate looks for are what these tests are about, not the matrix)."""
    import sys

    from sim_twin.training.matrix_gate import MatrixGate

    class Gate(MatrixGate):
        def command(self, onnx, seed, out):
            rep = {"pass": True, "profiles": [{"name": "nominal", "targets": [{"target_m": 10.0, "bars": {"accuracy": True}}]}]}
            return [sys.executable, "-c", f"import json; open({out!r}, 'w').write(json.dumps({rep!r}))"]

    return Gate(out_dir, "2d", seeds=[0, 1], workers=1, clock=lambda: 700.0, judge_after_pass=True)


def test_state_carries_the_candidate_under_test_that_the_resumed_gate_judges_again(tmp_path):
    """A run resumed on a second machine keeps the first machine's GPU record and log, and the gate's
    candidate under test (matrix_gate.json's pending) comes along whole: its ONNX file, its manifest
    (judging loads the policy through it) and its checkpoint (exporting it once it passed); the
    other candidates stay behind. Unpacked, a gate on that state judges the candidate again from the
    seed it had reached (a state carrying only the ONNX file left the resumed gate a matrix that
    could not load the policy)."""
    src = _run_with_pending(tmp_path, ["candidates/checkpoint_575.onnx", "candidates/checkpoint_575.json",
                                       "candidates/checkpoint_575.pt"])
    r = _state(tmp_path, str(src), "throw2d-x")
    assert r.returncode == 0, r.stderr
    assert "is not there" not in r.stderr
    tar = tmp_path / "runs" / "state" / "throw2d-x.tar"
    with tarfile.open(tar) as t:
        files = sorted(m.name for m in t.getmembers() if m.isfile())
    assert files == [f"runs/throw2d-x/{rel}" for rel in [
        "accelerators.json", "candidates/checkpoint_575.json", "candidates/checkpoint_575.onnx", "candidates/checkpoint_575.pt",
        "checkpoint.pt", "config.json", "logs/machine1.log.gz", "matrices/matrix_gate.json"]]

    machine2 = tmp_path / "machine2"
    machine2.mkdir()
    subprocess.run(["tar", "xf", str(tar)], cwd=machine2, check=True)
    gate = _passing_gate(machine2 / "runs" / "throw2d-x" / "matrices")
    assert gate.resume_pending()
    passed = gate.wait(60)
    assert passed is not None and passed["iteration"] == 575 and passed["train_wall_s"] == 646.0
    assert [(r.iteration, r.seed) for r in gate.results] == [(575, 1)]  # seed 0 had been met on the first machine


def _state_of_passes(tmp_path: Path, iterations: tuple[int, ...], name: str, passes: list[dict], pending: dict | None) -> Path:
    """A run with every file of the candidates ``iterations`` and a gate state holding ``passes`` (the first
    as ``passed``) and ``pending``, packed by ``state`` as NAME without a complaint and unpacked on a
    second machine; returns the unpacked run directory."""
    import json

    files = [f"candidates/checkpoint_{it}.{x}" for it in iterations for x in ("onnx", "json", "pt")]
    src = _run_with_pending(tmp_path, files)
    gate_json = src / "matrices" / "matrix_gate.json"
    state = json.loads(gate_json.read_text())
    state.update(passed=passes[0], passes=passes, pending=pending)
    gate_json.write_text(json.dumps(state))
    r = _state(tmp_path, str(src), name)
    assert r.returncode == 0 and "is not there" not in r.stderr, r.stderr
    machine2 = tmp_path / "machine2"
    machine2.mkdir()
    subprocess.run(["tar", "xf", str(tmp_path / "runs" / "state" / f"{name}.tar")], cwd=machine2, check=True)
    return machine2 / "runs" / name


def test_state_carries_the_candidates_that_met_the_bars_which_the_resumed_run_exports(tmp_path):
    """A run training past the bars (--no-stop-at-bars) exports the newest candidate that met them,
    a run stopping at them the first: the state carries both (with the one under test) whole, and not
    the passes between them, and a gate on the state unpacked under another name finds them."""
    passes = [{"iteration": it, "onnx": f"runs/throw2d-x/candidates/checkpoint_{it}.onnx", "train_wall_s": it * 1.0,
               "verdict_wall_s": it * 1.1} for it in (500, 800, 1000)]
    pending = {"iteration": 575, "onnx": "runs/throw2d-x/candidates/checkpoint_575.onnx", "train_wall_s": 575.0, "seed_index": 1}
    run2 = _state_of_passes(tmp_path, (500, 575, 800, 1000), "throw2d-y", passes, pending)
    kept = sorted(p.name for p in (run2 / "candidates").iterdir())
    assert kept == [f"checkpoint_{it}.{x}" for it in (1000, 500, 575) for x in ("json", "onnx", "pt")]
    gate = _passing_gate(run2 / "matrices")
    assert gate.passes[-1]["iteration"] == 1000 and gate.locate(gate.passes[-1]["onnx"]).with_suffix(".pt").exists()
    assert gate.locate(gate.passed["onnx"]).with_suffix(".pt").read_text() == "candidates/checkpoint_500.pt"


def test_a_state_without_the_candidates_manifest_says_so_and_the_resumed_gate_drops_it(tmp_path, caplog):
    """A candidate whose manifest is missing (a run directory trimmed by hand) is packed without it
    with a warning on stderr; the resumed gate drops it with a warning naming the file instead of
    starting a matrix that fails to load the policy, and takes new candidates."""
    src = _run_with_pending(tmp_path, ["candidates/checkpoint_575.onnx", "candidates/checkpoint_575.pt"])
    r = _state(tmp_path, str(src), "throw2d-x")
    assert r.returncode == 0, r.stderr
    assert "checkpoint_575.json is not there" in r.stderr
    machine2 = tmp_path / "machine2"
    machine2.mkdir()
    subprocess.run(["tar", "xf", str(tmp_path / "runs" / "state" / "throw2d-x.tar")], cwd=machine2, check=True)
    gate = _passing_gate(machine2 / "runs" / "throw2d-x" / "matrices")
    with caplog.at_level("WARNING", logger="sim_twin.training.matrix_gate"):
        assert not gate.resume_pending()
    assert "checkpoint_575.json not there" in caplog.text and not gate.busy
    assert gate.submit(600, str(machine2 / "c600.onnx"), 0.0)
    gate.stop()


def test_collect_names_each_machines_log_in_turn(tmp_path):
    """On a resumed run's machine the log is machine2 (machine1 came with the state), however often
    that machine collects."""
    work, out = tmp_path / "work", tmp_path / "out"
    out.mkdir()
    _run_dir(work, "resumed", card_iteration=None)
    (work / "runs" / "resumed" / "logs").mkdir()
    (work / "runs" / "resumed" / "logs" / "machine1.log.gz").write_text("first machine")
    for _ in range(2):
        assert _collect(work, out).returncode == 0
    with tarfile.open(out / "resumed.tar") as t:
        logs = sorted(m.name for m in t.getmembers() if "/logs/" in m.name)
        assert t.extractfile("runs/resumed/logs/machine1.log.gz").read() == b"first machine"
    assert logs == ["runs/resumed/logs/machine1.log.gz", "runs/resumed/logs/machine2.log.gz"]


def test_state_carries_the_pass_a_compared_run_exports(tmp_path):
    """With --gate-compare-with a run past the bars exports the pass worse than the deployed policy
    on the fewest cells (matrix_gate.choose_pass), here one between the first and the newest: the
    state carries it too."""
    passes = [{"iteration": it, "onnx": f"runs/throw2d-x/candidates/checkpoint_{it}.onnx", "train_wall_s": it * 1.0,
               "verdict_wall_s": it * 1.1, "worse_than_deployed": worse} for it, worse in ((500, 4), (800, 1), (1000, 3))]
    run2 = _state_of_passes(tmp_path, (500, 800, 1000), "throw2d-z", passes, None)
    kept = sorted(p.name for p in (run2 / "candidates").iterdir())
    assert kept == [f"checkpoint_{it}.{x}" for it in (1000, 500, 800) for x in ("json", "onnx", "pt")]


def test_a_run_tar_resumes_the_run_where_the_state_is_too_large_to_come_back(tmp_path):
    """A device call brings back files of 16 MiB at most: four runs' state.tar once did not come back.
    Over the limit (set to 1 byte here) collect leaves it out and says how to resume; each run's tar
    carries the candidates' checkpoints its state needs (the gate's passed and pending ones, not the
    others), so `state` on the unpacked run here packs the whole resume state."""
    import json
    import os
    import sys

    work, out = tmp_path / "work", tmp_path / "out"
    out.mkdir()
    _run_dir(work, "big", card_iteration=None)
    run = work / "runs" / "big"
    (run / "config.json").write_text("{}")
    for it in (50, 75):
        for x in ("onnx", "json", "pt"):
            (run / "candidates" / f"checkpoint_{it}.{x}").write_text(f"{it}.{x}")
    (run / "matrices").mkdir()
    (run / "matrices" / "matrix_gate.json").write_text(json.dumps({"results": [], "passed": {
        "iteration": 50, "onnx": "runs/big/candidates/checkpoint_50.onnx", "train_wall_s": 50.0}, "pending": {
        "iteration": 75, "onnx": "runs/big/candidates/checkpoint_75.onnx", "train_wall_s": 75.0, "seed_index": 0}}))
    env = {"PATH": f"{os.path.dirname(sys.executable)}:/usr/bin:/bin", "SLINGER_RUNS_WORK": str(work), "OUT": str(out),
           "SLINGER_STATE_MAX_BYTES": "1"}
    r = subprocess.run(["bash", str(SCRIPT), "collect"], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert not (out / "state.tar").exists() and "state.tar over 1 bytes, left out" in r.stdout
    with tarfile.open(out / "big.tar") as t:
        pts = sorted(m.name for m in t.getmembers() if m.name.endswith(".pt"))
    assert pts == ["runs/big/candidates/checkpoint_50.pt", "runs/big/candidates/checkpoint_75.pt", "runs/big/checkpoint.pt"]
    here = tmp_path / "here"
    here.mkdir()
    subprocess.run(["tar", "xf", str(out / "big.tar")], cwd=here, check=True)
    r = _state(here, "runs/big", "big")
    assert r.returncode == 0 and "is not there" not in r.stderr, r.stderr
    with tarfile.open(here / "runs" / "state" / "big.tar") as t:
        kept = sorted(m.name.rsplit("/", 1)[1] for m in t.getmembers() if "/candidates/" in m.name)
    assert kept == [f"checkpoint_{it}.{x}" for it in (50, 75) for x in ("json", "onnx", "pt")]
