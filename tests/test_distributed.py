"""Data-parallel training on torch.distributed: 2 local ranks on gloo, one thread each.

A tiny generated scene (8 views of 32x32, 200 primitives, densification inside the window so the
count changes): a 2-rank training equals a single-process training with the same total
batch_views, through `--nproc 2` and through `torchrun -m radfield`; a rank killed with SIGKILL
ends the job with one error line, and `radfield reconstruct` then resumes the run; continuing a
finished run to more steps under torchrun equals continuing it in a single process.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from radfield.core.trainer import launch
from radfield.core.trainer.distributed import compare_checksums
from radfield.core.trainer.loop import load_checkpoint
from radfield.demo.static import generate_scene

ITERATIONS = 40
SETS = ["--set", "init.num_points=200", "--set", "train.batch_views=2", "--set", "train.eval_every=0",
        "--set", "train.densify.start=10", "--set", "train.densify.stop=30", "--set", "train.densify.every=10",
        "--set", "train.densify.grad_threshold=1e-4", "--set", "train.checkpoint_every=10",
        "--set", "distributed.timeout=30", "--set", "distributed.sync_check_every=5"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def reconstruct_args(scene: Path, run: Path, iterations: int = ITERATIONS) -> list[str]:
    return ["reconstruct", str(scene), "-o", str(run), "--no-cage", "--until", "train",
            "--iterations", str(iterations), *SETS]


def radfield(*args, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "radfield", *args], env=ENV, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return generate_scene("blobs", tmp_path_factory.mktemp("dist") / "blobs", n_train=8, n_test=2, size=32)


@pytest.fixture(scope="module")
def single(scene, tmp_path_factory, run_radfield):
    """The single-process reference run directory."""
    run = tmp_path_factory.mktemp("single") / "run"
    assert run_radfield(*reconstruct_args(scene, run), "--quiet") == 0
    return run


def _log(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def assert_same_training(run: Path, reference: Path, iterations: int = ITERATIONS) -> None:
    state, log = load_checkpoint(run / "train" / "final_state.safetensors"), _log(run / "train" / "log.jsonl")
    ref_state = load_checkpoint(reference / "train" / "final_state.safetensors")
    ref_log = _log(reference / "train" / "log.jsonl")
    assert state.step == ref_state.step == iterations
    assert state.attrs["window"] and ref_state.attrs["window"]   # the default density window, carried to every rank
    counts = [r["primitives"] for r in ref_log]
    assert counts[0] == 200 and counts[-1] != 200  # densification changed the population ...
    assert [r["primitives"] for r in log] == counts  # ... identically on both
    for name, ref in ref_state.params.items():
        assert state.params[name].shape == ref.shape, name
        torch.testing.assert_close(state.params[name], ref, rtol=1e-4, atol=1e-5, msg=name)
    for name in ref_state.strategy:
        torch.testing.assert_close(state.strategy[name], ref_state.strategy[name], rtol=1e-4, atol=1e-6)
    for a, b in zip(log, ref_log):  # the logged loss is of the whole batch, reduced over the ranks
        assert a["loss"] == pytest.approx(b["loss"], rel=1e-4)


def test_nproc_equals_single_process(scene, single, tmp_path):
    run = tmp_path / "run"
    done = radfield(*reconstruct_args(scene, run), "--quiet", "--nproc", "2")
    assert done.returncode == 0, done.stderr
    assert "train ran" in done.stdout
    assert_same_training(run, single)
    # only rank 0 wrote into the run directory: nothing but the stages' folders, marker, config, lock
    assert sorted(p.name for p in run.iterdir()) == [".lock", "config.yaml", "data", "envelope", "hashes.json", "init",
                                                      "radfield-run.json", "sfm", "tetra", "train", "triangulate"]


def test_torchrun_continues_like_a_single_process(scene, single, tmp_path, capsys, run_radfield):
    """Continuing the finished single-process run to more steps: under torchrun rank 0 reads the
    final state and sends it to rank 1 (the path a resumed checkpoint takes too)."""
    alone, ranks, iterations = tmp_path / "alone", tmp_path / "ranks", ITERATIONS + 10
    shutil.copytree(single, alone)
    shutil.copytree(single, ranks)
    assert run_radfield(*reconstruct_args(scene, alone, iterations), "--quiet") == 0
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                           "-m", "radfield", *reconstruct_args(scene, ranks, iterations)],
                          env=ENV, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert f"train: continuing the finished run from step {ITERATIONS}" in done.stderr
    assert_same_training(ranks, alone, iterations)
    # cached for a single process too: the number of ranks is not part of the train stage's key
    capsys.readouterr()
    assert run_radfield(*reconstruct_args(scene, ranks, iterations), "--quiet") == 0
    assert "train cached" in capsys.readouterr().out


def test_batch_views_below_ranks_is_one_line(scene, tmp_path, capsys, run_radfield):
    assert run_radfield("reconstruct", str(scene), "-o", str(tmp_path / "run"), "--nproc", "2") == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("radfield: error: 2 ranks need train.batch_views >= 2")
    assert not (tmp_path / "run").exists()


def _rank_pid(launcher: int, local_rank: int) -> int | None:
    """The pid of the launcher's worker process with this LOCAL_RANK (read from /proc)."""
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            ppid = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
            environ = (proc / "environ").read_bytes().split(b"\0")
        except (OSError, IndexError, ValueError):
            continue
        if ppid == launcher and f"LOCAL_RANK={local_rank}".encode() in environ:
            return int(proc.name)
    return None


def test_killed_rank_fails_cleanly_and_the_run_resumes(scene, tmp_path, capsys, run_radfield):
    run, iterations = tmp_path / "run", 80
    job = subprocess.Popen([sys.executable, "-m", "radfield", *reconstruct_args(scene, run, iterations), "--quiet",
                            "--nproc", "2"], env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log, checkpoint = run / "train.work" / "log.jsonl", run / "train.work" / "checkpoint.safetensors"
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and job.poll() is None:
        if checkpoint.is_file() and log.is_file() and len(log.read_text().splitlines()) >= 12:
            break
        time.sleep(0.02)
    assert job.poll() is None, job.communicate()
    victim = _rank_pid(job.pid, 1)
    assert victim is not None
    os.kill(victim, signal.SIGKILL)
    killed = time.monotonic()
    out, err = job.communicate(timeout=60)
    assert time.monotonic() - killed < 30
    assert job.returncode == 1
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("radfield: error: rank 1 (pid") and "SIGKILL" in lines[0]
    assert "resume" in lines[0]
    step = load_checkpoint(checkpoint).step
    assert 10 <= step < iterations

    # a single process picks the run up from the 2-rank checkpoint and finishes it
    capsys.readouterr()
    assert run_radfield(*reconstruct_args(scene, run, iterations)) == 0
    assert f"train: resuming from the checkpoint at step {step}" in capsys.readouterr().err
    assert load_checkpoint(run / "train" / "final_state.safetensors").step == iterations
    assert [r["step"] for r in _log(run / "train" / "log.jsonl")] == list(range(1, iterations + 1))


def test_diverged_ranks_are_named():
    rows = [torch.tensor([3.0, 1.0, 2.0, 4.0, 0.5, 0.25], dtype=torch.float64) for _ in range(3)]
    compare_checksums(rows, ["means", "w1"], 100)  # equal: nothing
    rows[2] = rows[2].clone()
    rows[2][4] += 1e-12
    with pytest.raises(Exception, match=r"diverged at step 100: .* of rank 2 differ from rank 0's \(in w1\)"):
        compare_checksums(rows, ["means", "w1"], 100)


def test_failure_line_prefers_the_root_cause(tmp_path, monkeypatch, capsys):
    from torch.distributed.elastic.multiprocessing.errors import ProcessFailure

    # a rank's RadfieldError goes into torchelastic's error file; under --nproc it prints nothing
    error_file = tmp_path / "error.json"
    monkeypatch.setenv("TORCHELASTIC_ERROR_FILE", str(error_file))
    monkeypatch.setenv("RADFIELD_LAUNCHER", "1")
    with pytest.raises(SystemExit) as exit_:
        with launch._reported():
            raise launch.RadfieldError("train: rank 0: the gradient all-reduce at step 7 failed")
    assert exit_.value.code == 1 and capsys.readouterr().err == ""
    reported = ProcessFailure(0, 100, 1, str(error_file))
    terminated = ProcessFailure(1, 101, -signal.SIGTERM, "<N/A>")
    killed = ProcessFailure(2, 102, -signal.SIGKILL, "<N/A>")
    line = launch.failure_line
    assert line({0: reported, 1: terminated}, tmp_path) == "train: rank 0: the gradient all-reduce at step 7 failed"
    assert line({0: reported, 1: terminated, 2: killed}, tmp_path).startswith("rank 2 (pid 102) was killed by SIGKILL")
    assert line({1: terminated}, tmp_path).startswith("rank 1 (pid 101) was killed by SIGTERM")


def test_the_last_message_is_dropped_only_after_its_group(tmp_path):
    """The tensors of rank 0's last message stay referenced until the group is destroyed, then go.
    Dropped earlier, gloo's worker thread could free one while destroy_process_group joined it with
    the GIL held: with torch 2.4.1 rank 0 hung at its end in 2 of 11 runs of this file (in none of 14
    with them kept). A one-rank group here: the deadlock itself needs a race this cannot force."""
    import weakref

    from radfield.core.trainer import distributed

    torch.distributed.init_process_group("gloo", store=torch.distributed.FileStore(str(tmp_path / "store"), 1),
                                         rank=0, world_size=1)
    try:
        distributed.send("done", {"x": 1}, {"a": torch.arange(3.0)})
        sent = [weakref.ref(part) for part in distributed._last_message]
        assert len(sent) == 3 and all(ref() is not None for ref in sent)
    finally:
        distributed.disconnect()
    assert not torch.distributed.is_initialized() and all(ref() is None for ref in sent)
