"""Reconstruction over several ranks (`radfield reconstruct` under torchrun, or with `--nproc N`,
which starts the local ranks itself through torch's elastic launcher: standalone rendezvous on a
free port).

Rank 0 runs the pipeline as a single process would (it alone takes the run directory's lock and
writes into it); the other ranks only join the training (radfield.core.trainer.dataparallel) and exit
when rank 0 says it is done. A failure is one line `radfield: error: …` and exit status 1: under
torchrun every rank that notices it prints its line (and records it in torchrun's error file, so
torchrun's summary names it); with --nproc the workers only record it and the launcher prints
one line for the whole job.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

from radfield.core.trainer import distributed
from radfield.errors import RadfieldError

_LAUNCHED_HERE = "RADFIELD_LAUNCHER"  # set for the workers of --nproc: the launcher reports errors


def follower() -> bool:
    """Whether this process is a rank other than 0 of a torchrun job."""
    return distributed.launched() and int(os.environ.get("RANK", "0")) != 0


def check_ranks(cfg: dict, ranks: int) -> None:
    """Every rank renders at least one view per step."""
    batch = cfg["train"]["batch_views"]
    if ranks > batch:
        raise RadfieldError(f"{ranks} ranks need train.batch_views >= {ranks} (it is {batch}): each rank renders "
                            f"its share of a step's views; e.g. --set train.batch_views={ranks}")


def follow() -> None:
    """A rank other than 0: join, train when rank 0 says so, exit with rank 0's outcome."""
    with _reported():
        distributed.connect()
        done = False
        try:
            from radfield.core.trainer.dataparallel import follow as follow_rank0

            done = follow_rank0()
        finally:
            distributed.disconnect()
    if not done:
        sys.exit(1)  # rank 0 failed and reported it


@contextlib.contextmanager
def leading(cfg: dict) -> Iterator[None]:
    """Rank 0 of a torchrun job around the pipeline (nothing outside torchrun): join the other
    ranks, and tell them at the end whether the pipeline succeeded."""
    if not distributed.launched():
        yield
        return
    with _reported():
        world = distributed.connect(cfg["distributed"]["timeout"], cfg["distributed"]["sync_check_every"])
        outcome = "failed"
        try:
            check_ranks(cfg, world.size)
            cfg["device"] = str(world.device(cfg["device"]))
            yield
            outcome = "done"
        except RadfieldError as error:
            if isinstance(error, distributed.DistributedFailure) or \
                    isinstance(error.__cause__, distributed.DistributedFailure):
                outcome = None  # the group is broken: nobody to tell
            raise
        finally:
            if outcome is not None:
                with contextlib.suppress(RadfieldError):
                    distributed.send(outcome)
            distributed.disconnect()


def launch(nproc: int, cfg: dict, run_dir: Path, argv: list[str]) -> None:
    """Run `radfield ARGV` (this same command) as `nproc` local ranks (torch.distributed's elastic
    launcher, the engine behind torchrun) and wait for them; a failure becomes one RadfieldError line."""
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.elastic.multiprocessing.api import SignalException
    from torch.distributed.launcher.api import LaunchConfig, elastic_launch

    check_ranks(cfg, nproc)
    config = LaunchConfig(min_nodes=1, max_nodes=1, nproc_per_node=nproc, run_id=f"radfield-{uuid.uuid4().hex}",
                          rdzv_backend="c10d", rdzv_endpoint="localhost:0", max_restarts=0, monitor_interval=0.1)
    threads = os.environ.get("OMP_NUM_THREADS") or str(max(1, (os.cpu_count() or 1) // nproc))
    saved = {key: os.environ.get(key) for key in (_LAUNCHED_HERE, "OMP_NUM_THREADS")}
    os.environ.update({_LAUNCHED_HERE: "1", "OMP_NUM_THREADS": threads})
    elastic = logging.getLogger("torch.distributed.elastic")
    level = elastic.level
    elastic.setLevel(logging.CRITICAL)  # the agent's own warnings; the failure is reported below
    try:
        elastic_launch(config, sys.executable)("-m", "radfield", *argv)
    except ChildFailedError as error:
        raise RadfieldError(failure_line(error.failures, run_dir)) from None
    except SignalException:
        raise KeyboardInterrupt from None
    finally:
        elastic.setLevel(level)
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def failure_line(failures: dict, run_dir: Path) -> str:
    """One line for the failed ranks of a job ({rank: ProcessFailure}): a rank that died of a
    signal is the root cause; else the message of the lowest rank that reported one."""
    ranked = sorted(failures.items())
    killed = [(rank, f) for rank, f in ranked if f.exitcode < 0]
    # SIGTERM is what the agent sends the survivors when it tears the job down: the last resort
    signalled = [(rank, f) for rank, f in killed if f.exitcode != -signal.SIGTERM]
    if signalled:
        return _killed(*signalled[0], run_dir)
    for rank, failure in ranked:
        message = failure.message.get("message") if isinstance(failure.message, dict) else None
        if isinstance(message, str) and message.startswith("radfield: error: "):
            return message.removeprefix("radfield: error: ")
    if killed:
        return _killed(*killed[0], run_dir)
    rank, failure = ranked[0]
    return f"rank {rank} (pid {failure.pid}) exited with status {failure.exitcode}"


def _killed(rank: int, failure, run_dir: Path) -> str:
    return (f"rank {rank} (pid {failure.pid}) was killed by {failure.signal_name()}; the run directory "
            f"{run_dir} keeps its last checkpoint: run the same `radfield reconstruct` again to resume")


@contextlib.contextmanager
def _reported() -> Iterator[None]:
    """A RadfieldError of a rank: into torchrun's error file, and on stderr unless --nproc's
    launcher reports it; exit status 1. SIGTERM (the agent stopping the survivors of a failed
    job) ends the rank at once and quietly, instead of torch's stack dump."""
    signal.signal(signal.SIGTERM, lambda *_: os._exit(128 + signal.SIGTERM))
    try:
        yield
    except RadfieldError as error:
        message = str(error)
        path = os.environ.get("TORCHELASTIC_ERROR_FILE")
        if path:
            with contextlib.suppress(OSError):
                # torchelastic's own layout (errors/error_handler.py), so torchrun's summary shows it
                Path(path).write_text(json.dumps({"message": {"message": f"radfield: error: {message}", "extraInfo": {
                    "py_callstack": f"radfield: error: {message}", "timestamp": str(int(time.time()))}}}))
        if not os.environ.get(_LAUNCHED_HERE):
            print(f"radfield: error: {message}", file=sys.stderr, flush=True)
        sys.exit(1)
