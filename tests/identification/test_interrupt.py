"""Interrupting a fit loses nothing: Ctrl-C / SIGTERM stop after the current iteration and save a resumable
state; resuming it gives the same answer as an uninterrupted fit; the material file is never left corrupt."""

import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from empm_gym.cli import main
from empm_gym.identification.interrupt import StopRequest, stop_on_signals
from empm_gym.identification.offline import ResumeError, identify, read_resume_state
from empm_gym.sim import MaterialConfig, write_material

from . import scenes

E_TRUE = 5.0e4
# lr 0.5 makes Adam overshoot at iteration 3 (the loss goes up: back to the best point, momentum dropped,
# step halved), so a resume from iteration 3 on depends on all of Adam's bookkeeping, not only its moments
FITS = {"adam": dict(method="adam", lr=0.5, iters=6, stop_at=3),
        "cmaes": dict(method="cmaes", popsize=4, iters=5, stop_at=2)}


@pytest.fixture(scope="module")
def rope():
    return scenes.rope_lift(E=E_TRUE, frames=8, lift_frames=6)


def _kw(method):
    kw = {k: v for k, v in FITS[method].items() if k != "stop_at"}
    return dict(params=("E",), init={"E": E_TRUE / 3}, progress=False, **kw)


@pytest.fixture(scope="module")
def uninterrupted(rope):
    return {m: identify(rope.obs, rope.scene, **_kw(m)) for m in FITS}


def test_stop_on_signals_sets_the_request_then_a_second_signal_stops_hard():
    before_int, before_term = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with stop_on_signals() as stop:
        assert not stop.is_set()
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)
        assert stop.is_set() and stop.signum == signal.SIGTERM and stop.exit_code == 143
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
        assert stop.signum == signal.SIGTERM  # the first signal decides the exit code
    assert signal.getsignal(signal.SIGINT) is before_int and signal.getsignal(signal.SIGTERM) is before_term
    s = StopRequest()
    s.set(signal.SIGINT)
    assert s() and s.exit_code == 130 and s.signal_name == "SIGINT"


@pytest.mark.parametrize("method", list(FITS))
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_stops_after_the_iteration_and_resume_gives_the_uninterrupted_answer(rope, uninterrupted, tmp_path,
                                                                                    method, sig):
    full = uninterrupted[method]
    k = FITS[method]["stop_at"]
    seen = []

    def send_at_k(it, loss, vals):
        seen.append(it)
        if it == k:
            os.kill(os.getpid(), sig)

    with stop_on_signals() as stop:
        part = identify(rope.obs, rope.scene, callback=send_at_k, stop=stop, **_kw(method))
    assert stop.signum == sig
    assert seen == list(range(k + 1))  # the iteration in progress finished, no further one started
    assert not part.complete and part.iterations_done == k + 1 and part.iterations_requested == full.iterations_done
    assert part.loss_history == full.loss_history[: k + 1]
    assert part.loss == min(part.loss_history) and "resume" in part.extra
    if method == "adam":
        assert full.loss_history[k] > min(full.loss_history[:k])  # the overshoot happened before the stop

    path = tmp_path / "material.json"
    part.save(path)
    d = json.loads(path.read_text())
    assert d["fit"]["complete"] is False and d["fit"]["iterations_done"] == k + 1
    assert d["E"] == pytest.approx(part.params["E"])

    fit = read_resume_state(path)  # what `empm identify --resume` does
    with pytest.raises(ResumeError, match=rf"already holds {k + 1} iterations; ask for more than {k + 1}"):
        identify(rope.obs, rope.scene, resume=fit, **{**_kw(method), "iters": k + 1})
    res = identify(rope.obs, rope.scene, resume=fit, **_kw(method))
    assert res.complete and res.iterations_done == full.iterations_done and "resume" not in res.extra
    assert res.loss_history == pytest.approx(full.loss_history, rel=1e-9)
    assert res.params["E"] == pytest.approx(full.params["E"], rel=1e-9)
    if method == "cmaes":
        assert res.extra["evaluations"] == full.extra["evaluations"]
        assert res.extra["mean_history"] == [pytest.approx(m, rel=1e-9) for m in full.extra["mean_history"]]
    res.save(path)
    d = json.loads(path.read_text())
    assert d["fit"]["complete"] is True and d["fit"]["iterations_done"] == full.iterations_done
    assert "resume" not in d["fit"]
    with pytest.raises(ResumeError, match=r"material.json: it holds a complete fit"):
        read_resume_state(path)


def test_stop_before_the_first_iteration_returns_the_start(rope):
    res = identify(rope.obs, rope.scene, stop=lambda: True, **_kw("adam"))
    assert not res.complete and res.iterations_done == 0 and res.loss_history == []
    assert res.params == {"E": pytest.approx(E_TRUE / 3)} and math.isnan(res.loss)
    assert res.fit_section()["loss"] is None  # valid JSON


def test_resume_refuses_other_settings_data_or_too_few_iterations(rope, tmp_path):
    part = identify(rope.obs, rope.scene, stop=lambda: True, **_kw("cmaes"))  # a resumable state, 0 iterations
    fit = json.loads(json.dumps(part.fit_section()))
    with pytest.raises(ResumeError, match=r"other settings \(.*method: 'cmaes' then, 'adam' now"):
        identify(rope.obs, rope.scene, resume=fit, **_kw("adam"))
    with pytest.raises(ResumeError, match=r"popsize: 4 then, 6 now"):
        identify(rope.obs, rope.scene, resume=fit, **{**_kw("cmaes"), "popsize": 6})
    with pytest.raises(ResumeError, match=r"frames: 8 then, 6 now"):
        identify(rope.obs, rope.scene, resume=fit, frames=6, **_kw("cmaes"))
    other = scenes.rope_lift(E=E_TRUE, frames=8, lift_frames=6, seed=1)  # another "recording"
    with pytest.raises(ResumeError, match="fitted to other data"):
        identify(other.obs, other.scene, resume=fit, **_kw("cmaes"))
    with pytest.raises(ResumeError, match="holds no resumable state"):
        identify(rope.obs, rope.scene, resume={k: v for k, v in fit.items() if k != "resume"}, **_kw("cmaes"))
    fit["iterations_done"] = 2  # histories no longer match
    with pytest.raises(ResumeError, match="does not match its histories"):
        identify(rope.obs, rope.scene, resume=fit, **_kw("cmaes"))
    write_material(tmp_path / "plain.json", MaterialConfig(E=2e4))
    with pytest.raises(ResumeError, match=r"plain.json: it holds no fit section"):
        read_resume_state(tmp_path / "plain.json")
    with pytest.raises(ResumeError, match=r"none.json: material file does not exist"):
        read_resume_state(tmp_path / "none.json")


# ---- the command line, on a tiny `empm synth` recording -----------------------------------------------------

CLI_FIT = ["--dx", "0.02", "--particles-per-cell", "8", "--no-rrd"]


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    from empm_gym.perception.synth import synthesize

    return synthesize(tmp_path_factory.mktemp("rec") / "rope", "rope", frames=12, width=212, height=120,
                      progress=False)


class _Run:
    """``python -m empm_gym.cli identify ...`` in a subprocess; its stderr collected as it comes."""

    def __init__(self, args, cwd, watch: Path):
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.watch, self.snapshots = watch, []
        self.proc = subprocess.Popen([sys.executable, "-m", "empm_gym.cli", "identify", *map(str, args)], cwd=cwd,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
        self.buf = bytearray()
        self.reader = threading.Thread(target=self._pump, daemon=True)
        self.reader.start()

    def _pump(self):
        while True:
            chunk = os.read(self.proc.stderr.fileno(), 4096)
            if not chunk:
                return
            self.buf.extend(chunk)

    @property
    def err(self) -> str:
        return self.buf.decode(errors="replace")

    def _check_file(self):
        """The material file is whole JSON at every moment (atomic replacement)."""
        if self.watch.exists():
            text = self.watch.read_bytes()
            json.loads(text)
            if not self.snapshots or self.snapshots[-1] != text:
                self.snapshots.append(text)

    def wait_for(self, pattern, timeout=180.0):
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            self._check_file()
            m = re.search(pattern, self.err)
            if m:
                return m
            if self.proc.poll() is not None:
                break
            time.sleep(0.02)
        pytest.fail(f"no {pattern!r} on stderr (rc {self.proc.poll()}):\n{self.err[-3000:]}")

    def finish(self, timeout=180.0) -> int:
        t0 = time.monotonic()
        while self.proc.poll() is None and time.monotonic() - t0 < timeout:
            self._check_file()
            time.sleep(0.02)
        if self.proc.poll() is None:
            self.proc.kill()
            pytest.fail(f"identify did not stop within {timeout} s of the signal:\n{self.err[-3000:]}")
        self.reader.join(10)
        self._check_file()
        return self.proc.returncode


def _prior_file(path: Path) -> bytes:
    write_material(path, MaterialConfig(E=1234.0), {"method": "by hand"})
    return path.read_bytes()


@pytest.fixture(scope="module")
def interrupted(rec, tmp_path_factory):
    """A fit interrupted by SIGINT after its first iteration(s): (material file, stderr, exit code, snapshots)."""
    d = tmp_path_factory.mktemp("interrupted")
    out = d / "material.json"
    prior = _prior_file(out)
    run = _Run([rec, "--out", out, "--iters", 30, *CLI_FIT], d, out)
    run.wait_for(r"Ctrl-C stops after the current iteration and saves")
    run.wait_for(r"\b([1-9]\d*)/30\b")  # tqdm: an iteration finished
    run.proc.send_signal(signal.SIGINT)
    rc = run.finish()
    return out, run.err, rc, prior, run.snapshots


def test_cli_sigint_writes_the_fit_so_far(interrupted):
    out, err, rc, prior, snapshots = interrupted
    assert rc == 130, err[-3000:]
    assert "Traceback" not in err
    assert "fitting E (adam) on frames 0-7 of 12 (30 iterations)" in err
    lines = [s for s in err.replace("\r", "\n").splitlines() if "interrupted" in s]
    assert len(lines) == 1, lines
    m = re.fullmatch(r"empm identify: interrupted after (\d+) of 30 iterations; wrote (\S+) "
                     r"\(fit\.complete: false\); continue with --resume", lines[0].strip())
    assert m and m.group(2) == str(out), lines[0]
    n = int(m.group(1))
    assert 1 <= n < 30
    d = json.loads(out.read_text())
    f = d["fit"]
    assert f["complete"] is False and f["iterations_done"] == n and f["iterations_requested"] == 30
    assert len(f["loss_history"]) == n and f["resume"]["settings"]["method"] == "adam"
    assert d["E"] != 1234.0 and f["dx"] == 0.02
    assert snapshots[0] == prior and len(snapshots) == 2  # the old file, then the new one: nothing in between
    assert not [p for p in out.parent.iterdir() if p.name.endswith(".tmp")]
    assert not (out.parent / "material_fit.png").exists()  # the plots are skipped


def test_cli_resume_gives_the_uninterrupted_answer(interrupted, rec, tmp_path, capsys):
    src, _, rc, _, _ = interrupted
    assert rc == 130
    out = tmp_path / "material.json"
    shutil.copy(src, out)
    n = json.loads(out.read_text())["fit"]["iterations_done"]
    assert main(["identify", str(rec), "--out", str(out), "--resume", "--iters", str(n + 1), "--quiet",
                 *CLI_FIT]) == 0
    err = capsys.readouterr().err
    assert f"(iterations {n + 1}-{n + 1} of {n + 1}, resuming {out})" in err
    full = tmp_path / "full.json"
    assert main(["identify", str(rec), "--out", str(full), "--iters", str(n + 1), "--quiet", *CLI_FIT]) == 0
    a, b = json.loads(out.read_text()), json.loads(full.read_text())
    assert a["fit"]["complete"] is True and a["fit"]["iterations_done"] == n + 1 and "resume" not in a["fit"]
    # two processes: the same to float32 rounding (a parallel test run measured 2e-7 apart)
    assert a["fit"]["loss_history"] == pytest.approx(b["fit"]["loss_history"], rel=1e-5)
    assert a["E"] == pytest.approx(b["E"], rel=1e-5)
    # a complete file is not resumed
    before = out.read_bytes()
    assert main(["identify", str(rec), "--out", str(out), "--resume", "--quiet", *CLI_FIT]) == 2
    err = capsys.readouterr().err
    assert f"cannot resume from {out}: it holds a complete fit ({n + 1} iterations)" in err
    assert out.read_bytes() == before


def test_cli_resume_refuses_other_options_and_data(interrupted, rec, tmp_path, capsys):
    out = tmp_path / "material.json"
    shutil.copy(interrupted[0], out)
    before = out.read_bytes()
    assert main(["identify", str(rec), "--out", str(out), "--resume", "--method", "cmaes", "--quiet",
                 *CLI_FIT]) == 2
    err = capsys.readouterr().err
    assert f"empm identify: error: cannot resume from {out}: it was fitted with other settings" in err
    assert "method: 'adam' then, 'cmaes' now" in err
    assert main(["identify", str(rec), "--out", str(out), "--resume", "--quiet", "--dx", "0.025",
                 "--particles-per-cell", "8", "--no-rrd"]) == 2
    assert f"cannot resume from {out}: it was fitted to other data" in capsys.readouterr().err
    assert main(["identify", str(rec), "--out", str(tmp_path / "none.json"), "--resume"]) == 2
    assert "none.json: material file does not exist" in capsys.readouterr().err
    assert main(["identify", str(rec), "--out", str(out), "--resume", "--online"]) == 2
    assert "does not apply to --online" in capsys.readouterr().err
    assert out.read_bytes() == before


def test_cli_sigterm_before_the_first_iteration_leaves_the_file(rec, tmp_path):
    out = tmp_path / "material.json"
    prior = _prior_file(out)
    run = _Run([rec, "--out", out, "--iters", 30, "--quiet", *CLI_FIT], tmp_path, out)
    run.wait_for(r"Ctrl-C stops after the current iteration and saves")
    run.proc.send_signal(signal.SIGTERM)
    rc = run.finish()
    assert rc == 143, run.err[-3000:]
    assert "Traceback" not in run.err
    assert f"empm identify: interrupted before an iteration finished; {out} left as it was" in run.err
    assert out.read_bytes() == prior and run.snapshots == [prior]


def test_cli_resume_keeps_the_time_budget_plan(rec, tmp_path, capsys):
    """A fit planned for a time budget (here a tighter grid) resumes on the same plan, read from the file,
    whatever the budget and the machine's speed are when it resumes."""
    out = tmp_path / "material.json"
    run = _Run([rec, "--out", out, "--iters", 30, "--dx", "0.02", "--no-rrd", "--budget-min", "0.001"], tmp_path,
               out)
    run.wait_for(r"Ctrl-C stops after the current iteration and saves")
    run.wait_for(r"\b([1-9]\d*)/30\b")
    run.proc.send_signal(signal.SIGINT)
    assert run.finish() == 130, run.err[-3000:]
    assert "planned instead" in run.err and "a grid 4 cells beyond the observed motion" in run.err
    fit = json.loads(out.read_text())["fit"]
    n = fit["iterations_done"]
    assert fit["plan"]["motion_margin"] == 0.0 and fit["complete"] is False
    assert main(["identify", str(rec), "--out", str(out), "--resume", "--iters", str(n + 1), "--dx", "0.02",
                 "--no-rrd", "--quiet", "--no-uncertainty"]) == 0, capsys.readouterr().err[-3000:]
    fit = json.loads(out.read_text())["fit"]
    assert fit["complete"] is True and fit["iterations_done"] == n + 1 and fit["plan"]["motion_margin"] == 0.0
