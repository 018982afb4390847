"""Site-matrix gate of a training run: the site matrix of new checkpoints runs on the CPU cores
beside the training, and the run stops at the first checkpoint that meets every bar.

One candidate at a time: when the gate is idle, the training hands it its newest exported
checkpoint (older ones that came while a matrix ran are skipped). The candidate's matrix runs seed
by seed (``slinger evaluate --matrix --seed s``, sim_twin.evaluation.matrix, in a child process with
its own worker pool; the first seed's with ``--release-sweep``, the policy validation's twin sweep
over the declared target range, so that a candidate that passes can also be promoted); a seed that misses a
bar ends that candidate. A candidate that meets every bar on
every seed has *passed*. By default the gate judges nothing after the first candidate that passed
(the training stops there); with ``judge_after_pass`` it goes on judging newer checkpoints, for a
training that runs past the bars (``slinger train --no-stop-at-bars``), and ``passes`` lists every
candidate that passed. The state (every verdict, and the candidate under test with the seed it is
at) is saved to ``<dir>/matrix_gate.json`` after every change so a resumed training keeps it: a
resumed training's gate judges the candidate that was under test when the run stopped again from the
seed it had reached (:meth:`MatrixGate.resume_pending`), where its ONNX file came along.

With ``compare_with`` (the deployed policy's site matrices of the gate's seeds, ``slinger train
--gate-compare-with``) every candidate that passed is also compared with the deployed policy by the
paired deploy test on the gate's seeds (sim_twin.evaluation.matrix_compare: the cells where it lands
further off, Holm-corrected); its entry in ``passes`` records ``worse_than_deployed`` (the count) and
``worse_cells``, and a run past the bars exports the pass with the fewest such cells, the newest among
equals (:func:`choose_pass`), instead of the newest. Why: late in a run a far cell's landing bias moves
by several centimetres from checkpoint to checkpoint (throw2d-scratch-n1's nominal 10 m bias +0.017 to
+0.157 m, seed 0), so the newest pass is one draw of that motion; a deployable policy is one no worse
than the deployed on any cell (docs/training.md, "Deploying a new version"). A run resumed with
``compare_with`` that it did not have before (it stopped at the bars, say) has its earlier passes compared
when the gate loads its state, from the matrices in ``out_dir``, so that they rank with the new ones.

:meth:`MatrixGate.watch` collects verdicts on a thread of its own as soon as a matrix process ends,
so a verdict is on disk even when the training is stopped (or its machine taken away) before its next
checkpoint; the training loop then only reads ``passed`` and hands over candidates.
"""

from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

PENDING_KEYS = ("iteration", "onnx", "train_wall_s", "seed_index")
"""What ``matrix_gate.json``'s ``pending`` keeps of the candidate under test (a resumed run's gate
judges it again from ``seed_index``)."""

CANDIDATE_SUFFIXES = (".onnx", ".json", ".pt")
"""The files of one candidate, ``candidates/checkpoint_<iteration>`` with these suffixes: the ONNX file
and its manifest, which judging it needs (``slinger evaluate`` loads the policy through its
manifest), and the checkpoint, which exporting it needs once it passed (``TrainingRun.finish``). A
state that resumes a run carries all three of the candidate under test, of the first and the newest
candidate that passed and of the one :func:`choose_pass` picks (``tests/benchmarks/device_runs.sh state``)."""


@dataclass
class MatrixResult:
    """Verdict of one (candidate, seed) site matrix."""

    iteration: int
    seed: int
    passed: bool
    missing_cells: int
    """Cells (profile x target) missing at least one bar."""
    matrix_path: str
    train_wall_s: float
    """Training wall time at the checkpoint [s]."""
    verdict_wall_s: float
    """Training wall time when the verdict came [s]."""
    misses: list[str] = field(default_factory=list)


def summarise_matrix(report: dict) -> tuple[int, list[str]]:
    """(cells missing a bar, "profile@target: bar,..." strings) of a sim_twin.evaluation.matrix report;
    a failed release sweep (``release_sweep``, the gate's matrices) counts as one more, "release sweep: <why>"."""
    misses = []
    sweep = report.get("release_sweep")
    if sweep and not sweep["passed"]:
        misses.append(f"release sweep: {sweep['reason']}")
    for p in report["profiles"]:
        for t in p["targets"]:
            bad = [k for k, v in t["bars"].items() if not v]
            if bad:
                misses.append(f"{p['name']}@{t['target_m']:g}: {','.join(bad)}")
    return len(misses), misses


def matrix_file_name(mode: str, iteration: int, seed: int) -> str:
    """The gate's name for the site matrix of ``iteration`` on ``seed``:
    ``site_matrix_<mode>_it<iteration>[_seed<seed>].json`` (no suffix for seed 0)."""
    return f"site_matrix_{mode}_it{iteration}" + (f"_seed{seed}" if seed else "") + ".json"


def parse_matrix_file_name(name: str) -> tuple[int, int]:
    """(iteration, seed) of a :func:`matrix_file_name`. Raises ValueError on any other name."""
    m = re.fullmatch(r"site_matrix_[23]d_it(\d+)(?:_seed(\d+))?\.json", name)
    if not m:
        raise ValueError(f"{name}: expected site_matrix_<mode>_it<N>[_seed<S>].json")
    return int(m.group(1)), int(m.group(2) or 0)


def saved_passes(state: dict) -> list[dict]:
    """Every pass of a saved ``matrix_gate.json`` (``state``), oldest first: its ``passes``, or for a
    state written before the gate kept them, its one ``passed`` (none where that is null)."""
    return state.get("passes") or ([state["passed"]] if state.get("passed") else [])


def _recorded_file(recorded: str, directory: Path) -> Path:
    """A file a saved gate state names: the path it recorded where that exists, else the file of that
    name in ``directory`` (a run resumed under another working directory or name, from a state that
    carried it: ``device_runs.sh state``). The path returned may not exist."""
    path = Path(recorded)
    return path if path.exists() else directory / path.name


def choose_pass(passes: list[dict]) -> dict | None:
    """The pass a run past the bars exports: where the gate compared the passes with the deployed
    policy (``worse_than_deployed`` not None), the one with the fewest cells worse, the newest among
    equals; passes without a comparison (older states, a failed comparison) only where none has
    one; else the newest. None for no pass."""
    if not passes:
        return None
    compared = [p for p in passes if p.get("worse_than_deployed") is not None]
    if compared:
        return min(reversed(compared), key=lambda p: p["worse_than_deployed"])  # min keeps the first: the newest
    return passes[-1]


GATE_NICENESS = 10
"""How much lower than the training process the site-matrix processes run (Unix niceness)."""


class MatrixGate:
    """Background site matrices of training checkpoints (see module doc).

    Args:
        out_dir: where matrices (``site_matrix_<mode>_it<iter>[_seed<s>].json/.md/.png``) and
            ``matrix_gate.json`` go.
        mode: "2d" or "3d".
        seeds: start-pose seeds every bar must be met on, in the order they are run.
        throws: throws per (profile, target) cell (the bars are defined for 100).
        targets: target spec for ``slinger evaluate --targets`` (default the matrix's).
        workers: processes of the matrix's pool (default all cores but ``reserve_cores``).
        reserve_cores: cores left to the training process when ``workers`` is not given.
        clock: function returning the training wall time now [s].
        judge_after_pass: keep judging new candidates after one passed (see module doc).
        compare_with: the deployed policy's site-matrix reports with per-throw data, one per seed in
            ``seeds``' order, to compare every pass with (see module doc); None: no comparison.

    Raises:
        ValueError: no seeds or fewer than 1 throw; ``compare_with`` not one report per seed, or a
            report that is not JSON, of another mode or of another start-pose seed.
        OSError: a ``compare_with`` file cannot be read.
    """

    def __init__(self, out_dir: Path, mode: str, seeds: list[int], throws: int = 100, targets: str | None = None,
                 workers: int | None = None, reserve_cores: int = 3, clock=None, judge_after_pass: bool = False,
                 compare_with: list[Path] | None = None):
        if not seeds:
            raise ValueError("the gate needs at least one seed")
        if throws < 1:
            raise ValueError("throws must be >= 1")
        if compare_with and len(compare_with) != len(seeds):
            raise ValueError(f"compare_with: {len(compare_with)} site matrices for {len(seeds)} gate seeds {seeds}: "
                             "give the deployed policy's matrix of each gate seed, in their order")
        self._deployed = [self._deployed_matrix(Path(p), mode, seed) for p, seed in zip(compare_with or [], seeds)]
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.mode, self.seeds, self.throws, self.targets = mode, list(seeds), throws, targets
        self.workers = workers or max(1, (os.cpu_count() or 1) - reserve_cores)
        self.clock = clock or time.time
        self.state_path = self.out_dir / "matrix_gate.json"
        self.results: list[MatrixResult] = []
        self.passed: dict | None = None  # {"iteration", "onnx", "train_wall_s"} of the first candidate that passed
        self.passes: list[dict] = []  # every candidate that passed, oldest first (the same dicts)
        self.judge_after_pass = judge_after_pass
        self._proc: subprocess.Popen | None = None
        self._cand: dict | None = None  # {"iteration", "onnx", "train_wall_s", "seed_index", "out"}
        self._lock = threading.RLock()  # the training's thread and the watch thread share the state
        self._watcher: threading.Thread | None = None
        self._unwatch = threading.Event()
        self._pending: dict | None = None
        if self.state_path.exists():
            st = json.loads(self.state_path.read_text())
            self.results = [MatrixResult(**r) for r in st.get("results", [])]
            self.passed = st.get("passed")
            self.passes = saved_passes(st)
            self._pending = st.get("pending")  # the candidate under test when the state was saved
        if self._deployed:  # passes of a run resumed with --gate-compare-with it did not have: rank them too
            for p in self.passes:
                if "worse_than_deployed" not in p:
                    p.update(self._compare(p["iteration"]))

    @staticmethod
    def _deployed_matrix(path: Path, mode: str, seed: int) -> dict:
        try:
            rep = json.loads(path.read_text())
        except ValueError as e:
            raise ValueError(f"{path}: not a site-matrix report ({e})") from e
        if rep.get("mode") != mode or int(rep.get("seed", -1)) != seed:
            raise ValueError(f"{path}: the site matrix of mode {rep.get('mode')} on seed {rep.get('seed')}, "
                             f"not {mode} on gate seed {seed}")
        return rep

    def _compare(self, iteration: int) -> dict:
        """``{"worse_than_deployed": n, "worse_cells": ["profile@target", ...]}`` of the passed
        candidate ``iteration`` against the deployed policy's matrices (module doc; a candidate that fails
        more often over all cells counts one more, ``"all cells@success"``); n None with the reason where
        the comparison failed (logged: the pass stands, it only ranks last)."""
        from sim_twin.evaluation.matrix_compare import compare

        try:
            mine = {r.seed: _recorded_file(r.matrix_path, self.out_dir) for r in self.results if r.iteration == iteration}
            comp = compare(self._deployed, [json.loads(mine[s].read_text()) for s in self.seeds])
        except (OSError, ValueError, KeyError) as e:
            log.error("iteration %d: the paired test against the deployed policy failed: %s", iteration, e)
            return {"worse_than_deployed": None, "worse_cells": [], "compare_error": str(e)}
        worse = [f"{c.profile}@{c.target_m:g}" for c in comp.cells if c.worse]
        if comp.fails_more:  # failures spread over the cells (matrix_compare's pooled success test) count as one more
            worse.append("all cells@success")
        log.info("iteration %d: worse than the deployed policy on %d cells by the paired test%s", iteration, len(worse),
                 f" ({', '.join(worse)})" if worse else "")
        return {"worse_than_deployed": len(worse), "worse_cells": worse}

    @property
    def busy(self) -> bool:
        """A candidate's matrix is running."""
        return self._cand is not None

    def submit(self, iteration: int, onnx: Path, train_wall_s: float) -> bool:
        """Start the matrix of this candidate if the gate is idle; returns whether it started."""
        with self._lock:
            if self.busy or (self.passed and not self.judge_after_pass):
                return False
            self._cand = {"iteration": int(iteration), "onnx": str(onnx), "train_wall_s": float(train_wall_s), "seed_index": 0}
            self._start_seed()
            return True

    def resume_pending(self) -> bool:
        """Judge again the candidate that was under test when the saved state was written (a
        training stopped, or its machine taken away, while a matrix ran), from the seed it had
        reached: the seeds it met stay met. Call it once, before :meth:`watch`, in a resumed run.
        The ONNX file is looked for where the state names it, else in ``candidates/`` beside the
        gate's directory (a run resumed under another name). Returns whether a matrix started; a
        candidate missing any of its files (:data:`CANDIDATE_SUFFIXES`: a state packed without
        them) is dropped with a warning naming them, instead of starting a matrix that cannot load
        the policy."""
        with self._lock:
            cand, self._pending = self._pending, None
            if cand is None or self.busy or (self.passed and not self.judge_after_pass):
                return False
            onnx = self.locate(cand["onnx"])
            cand = {**cand, "onnx": str(onnx)}
            missing = [str(onnx.with_suffix(x)) for x in CANDIDATE_SUFFIXES if not onnx.with_suffix(x).exists()]
            if missing:
                log.warning("site matrix of iteration %d is not judged again: %s not there", cand["iteration"], ", ".join(missing))
                return False
            self._cand = {k: cand[k] for k in PENDING_KEYS}
            log.info("judging iteration %d again from seed %d (under test when the run stopped)",
                     cand["iteration"], self.seeds[cand["seed_index"]])
            self._start_seed()
            return True

    def locate(self, onnx: str) -> Path:
        """Where a candidate's ONNX file named in the saved state is now: the path the state names
        where that exists, else ``candidates/<file name>`` beside the gate's directory (a run resumed
        under another directory or name, from a state that carried it: ``device_runs.sh state``).
        The path returned may not exist (a state packed without the candidate)."""
        return _recorded_file(onnx, self.out_dir.parent / "candidates")

    def exportable_passes(self) -> list[dict]:
        """The passes (oldest first) whose checkpoint is here (:meth:`locate`'s ONNX path with the
        suffix ``.pt``): ``finish`` chooses among these, since a run resumed from a state packed
        without a pass's checkpoint cannot export that pass. Empty where none is here."""
        return [p for p in self.passes if self.locate(p["onnx"]).with_suffix(".pt").exists()]

    def _candidate(self) -> dict:
        """The checkpoint under test (only called while one is).

        Raises:
            RuntimeError: no candidate (a bug of the caller).
        """
        if self._cand is None:
            raise RuntimeError("matrix gate: no checkpoint under test")
        return self._cand

    def _out(self, it: int, seed: int) -> Path:
        return self.out_dir / matrix_file_name(self.mode, it, seed)

    def command(self, onnx: str, seed: int, out: str) -> list[str]:
        """The child process that writes the site matrix of ``onnx`` on ``seed`` to ``out``; on the
        gate's first seed the release sweep first (its throws do not depend on the matrix seed, and a
        failed sweep ends the candidate at its first seed)."""
        cmd = [sys.executable, "-m", "sim_twin.evaluation.cli", "--policy", onnx, "--matrix",
               *(["--release-sweep"] if seed == self.seeds[0] else []), "--seed", str(seed),
               "--throws", str(self.throws), "--workers", str(self.workers), "--out", out]
        return cmd + (["--targets", self.targets] if self.targets else [])

    def _start_seed(self) -> None:
        c = self._candidate()
        seed = self.seeds[c["seed_index"]]
        c["out"] = str(self._out(c["iteration"], seed))
        cmd = self.command(c["onnx"], seed, c["out"])
        env = {**os.environ, "CUDA_VISIBLE_DEVICES": "", "JAX_PLATFORMS": "cpu", "OMP_NUM_THREADS": "1"}
        logf = open(self.out_dir / "matrix_gate.log", "a")
        log.info("site matrix of iteration %d, seed %d started (%d workers)", c["iteration"], seed, self.workers)
        self._proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, env=env)
        logf.close()
        self._lower_priority(self._proc.pid)
        self.save()  # the candidate under test and its seed: a resumed run judges it again from there

    def _lower_priority(self, pid: int) -> None:
        """Raise the matrix process's niceness by GATE_NICENESS (its pool inherits it), so that the
        training process keeps the cores it launches its GPU work from: with 13 matrix processes
        at equal priority on a 16-core machine, training ran at 0.36-0.46 M control steps/s against
        0.51-0.58 M/s before the gate started (throw2d-scratch-m's README, lab notebook: policies/training/ARCHIVE.md).
        The process is new (still starting Python), so its pool starts after this."""
        try:
            os.setpriority(os.PRIO_PROCESS, pid, os.getpriority(os.PRIO_PROCESS, 0) + GATE_NICENESS)
        except OSError as e:  # the process already ended, or a platform without priorities
            log.warning("matrix process %d keeps its priority: %s", pid, e)

    def poll(self) -> dict | None:
        """Collect a finished matrix, start the candidate's next seed if it passed; returns
        ``self.passed`` (the first candidate that met every bar on every seed) or None.

        A matrix process that failed or wrote no readable report ends its candidate with no verdict
        (logged with the path of ``matrix_gate.log``); the gate is idle again."""
        with self._lock:
            return self._poll()

    def _poll(self) -> dict | None:
        if self._proc is None or self._proc.poll() is None:
            return self.passed
        c, rc = self._candidate(), self._proc.returncode
        self._proc = None
        seed = self.seeds[c["seed_index"]]
        out = Path(c["out"])
        try:
            if rc != 0:
                raise ValueError(f"exit {rc}")
            rep = json.loads(out.read_text())
            n_miss, misses = summarise_matrix(rep)
            passed = bool(rep["pass"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.error("site matrix of iteration %d seed %d failed (%s); see %s", c["iteration"], seed, e,
                      self.out_dir / "matrix_gate.log")
            self.save(idle=True)  # not judged again on a resume either
            self._cand = None
            return self.passed
        res = MatrixResult(c["iteration"], seed, passed, n_miss, str(out), c["train_wall_s"], float(self.clock()), misses)
        self.results.append(res)
        log.info("site matrix of iteration %d seed %d: %s (%d cells miss a bar)", c["iteration"], seed,
                 "every bar met" if res.passed else "missed", n_miss)
        next_seed = res.passed and c["seed_index"] + 1 < len(self.seeds)
        if res.passed and not next_seed:
            self.passes.append({"iteration": c["iteration"], "onnx": c["onnx"], "train_wall_s": c["train_wall_s"],
                                "verdict_wall_s": res.verdict_wall_s, **(self._compare(c["iteration"]) if self._deployed else {})})
            self.passed = self.passed or self.passes[-1]
        if next_seed:
            c["seed_index"] += 1
            self._start_seed()  # saves the verdict with the candidate at its next seed
        else:
            self.save(idle=True)  # on disk before the gate reads idle: a reader who sees busy False finds the verdict
            self._cand = None
        return self.passed

    def watch(self, interval_s: float = 1.0) -> None:
        """Poll on a daemon thread every ``interval_s`` seconds until :meth:`stop`, so that each
        verdict is recorded (and the next seed started) when its matrix process ends rather than
        when the training next calls :meth:`poll`. Calling it again while watching does nothing."""
        if self._watcher is not None:
            return
        self._unwatch.clear()

        def loop() -> None:
            while not self._unwatch.wait(interval_s):
                self.poll()

        self._watcher = threading.Thread(target=loop, name="matrix-gate-watch", daemon=True)
        self._watcher.start()

    def wait(self, timeout_s: float) -> dict | None:
        """Poll until the gate is idle or ``timeout_s`` passed; returns ``self.passed``."""
        end = time.time() + timeout_s
        while self.busy and time.time() < end:
            self.poll()
            time.sleep(1.0)
        return self.passed

    def stop(self) -> None:
        """Stop watching and terminate a running matrix (its result is dropped)."""
        if self._watcher is not None:
            self._unwatch.set()
            self._watcher.join()
            self._watcher = None
        with self._lock:
            if self._proc is not None and self._proc.poll() is None:
                self._proc.terminate()
                try:
                    self._proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    self._proc.kill()
            self._proc, self._cand = None, None

    def save(self, idle: bool = False) -> None:
        """Write every verdict, ``passed``, ``passes`` and ``pending`` (the candidate under test:
        ``iteration``, ``onnx``, ``train_wall_s``, ``seed_index``; null when idle, or with ``idle``: the
        candidate's last verdict is in) to ``matrix_gate.json`` (whole file, replaced atomically so a
        reader never sees half of it)."""
        with self._lock:
            tmp = self.state_path.with_suffix(".json.tmp")
            pending = {k: self._cand[k] for k in PENDING_KEYS} if self._cand and not idle else None
            tmp.write_text(json.dumps(
                {"mode": self.mode, "seeds": self.seeds, "throws": self.throws, "passed": self.passed, "passes": self.passes,
                 "pending": pending, "results": [asdict(r) for r in self.results]}, indent=2) + "\n")
            tmp.replace(self.state_path)
