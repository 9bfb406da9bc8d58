"""Data-parallel training on torch.distributed (c10d): the process group, the per-step
collectives, the parameter checksum and rank 0's messages to the other ranks.

The ranks come from torchrun (or `radfield reconstruct --nproc N`, which starts them through
torch's own elastic launcher): RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT in the
environment. Outside it (WORLD_SIZE unset or 1) nothing here creates a process group and the
trainer runs exactly as a single process.

Two groups with two timeouts:
- the default group (gloo, CPU tensors, WAIT_TIMEOUT = 7 days) carries rank 0's messages: the
  other ranks wait there while rank 0 runs the stages before and after training (SfM and tetra
  can take hours on a large capture). A rank that dies is still seen at once: gloo's sockets
  close with the process, and torchrun's elastic agent tears the job down when a worker fails;
- the training group (NCCL for CUDA tensors, gloo for CPU ones, `distributed.timeout` seconds)
  carries the per-step all-reduce and the checksums, so a rank that hangs fails the step.

Per step (StepSync): each rank renders its share views[rank::world] of the step's views (the
same list on every rank: views_for_step is a function of seed and step), then ONE all-reduce
(SUM) of one flat buffer holding every parameter gradient, the step's increments of the
strategy's sum accumulators and the loss/PSNR sums; every rank then applies the same Adam step
to the same summed gradients. The running accumulators are never reduced themselves (that would
count earlier steps again): only the increments since the last reduce are.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from datetime import timedelta

import torch
import torch.distributed as dist

from radfield.errors import RadfieldError

WAIT_TIMEOUT = timedelta(days=7)  # rank 0's own stages; a dead rank closes its sockets, it is not waited for
DEFAULT_TIMEOUT = 300.0           # seconds a training collective waits (pipeline.yaml: distributed.timeout)
DEFAULT_CHECK_EVERY = 100         # steps between parameter checksums (distributed.sync_check_every)
RESUME_HINT = "the run directory keeps its last checkpoint: run the same `radfield reconstruct` again to resume"


class DistributedFailure(RadfieldError):
    """A collective failed: another rank died, or did not answer within the timeout."""


@dataclass
class World:
    """This process's place among the ranks. `size == 1`: a single process, no process group."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    timeout: float = DEFAULT_TIMEOUT
    check_every: int = DEFAULT_CHECK_EVERY
    group: object = None  # the training group (set by start_training)
    stats: dict = field(default_factory=lambda: {"steps": 0, "reduce_seconds": 0.0, "reduce_bytes": 0})

    def device(self, device: str | torch.device) -> torch.device:
        """The device of this rank: cuda means one GPU per local rank (cuda:LOCAL_RANK)."""
        device = torch.device(device)
        return torch.device("cuda", self.local_rank) if device.type == "cuda" and self.size > 1 else device


_current = World()


def current() -> World:
    """The world `connect` joined (a single process when it was not called)."""
    return _current


def launched() -> bool:
    """Whether this process is one of several ranks started by torchrun (or --nproc)."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def connect(timeout: float = DEFAULT_TIMEOUT, check_every: int = DEFAULT_CHECK_EVERY) -> World:
    """Join the process group that torchrun describes in the environment (gloo, long timeout:
    see the module docstring); a no-op single World outside torchrun."""
    global _current
    if not launched():
        _current = World()
        return _current
    rank, size = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    if not dist.is_initialized():
        try:
            dist.init_process_group("gloo", timeout=WAIT_TIMEOUT)
        except (RuntimeError, ValueError) as error:
            raise DistributedFailure(f"rank {rank}: could not join the other ranks ({_first_line(error)})") from None
    _current = World(rank, size, int(os.environ.get("LOCAL_RANK", "0")), float(timeout), int(check_every))
    return _current


# The tensors of the last message sent or received, kept until the group is destroyed. A tensor
# whose Python object is dropped while gloo's worker thread still holds it is freed by that
# thread, which must take the GIL to do so; destroying the group joins that thread while holding
# the GIL. Both wait forever (with torch 2.4.1 rank 0 hung in destroy_process_group after its last
# message in 2 of 11 runs of tests/test_distributed.py: the worker in PyObjectSlot's decref, the
# main thread in ~ProcessGroupGloo's join; none in 14 with the tensors kept). Kept here, their last
# reference is dropped by this thread, after the join.
_last_message: tuple[torch.Tensor, ...] = ()


def disconnect() -> None:
    """Leave the process group (after the last message); the world is a single process again."""
    global _current, _last_message
    if dist.is_initialized():
        with contextlib.suppress(RuntimeError, ValueError):
            dist.destroy_process_group()
    _last_message = ()
    _current = World()


def start_training(world: World, device: torch.device) -> None:
    """Create the training group: NCCL for a CUDA device, gloo otherwise, with world.timeout."""
    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(device)
    with _collective(world, "creating the training group", None):
        world.group = dist.new_group(backend=backend, timeout=timedelta(seconds=world.timeout))


# --- rank 0's messages (no pickle: a JSON header and the tensors' raw bytes) ----------------

def send(kind: str, meta: dict | None = None, tensors: dict[str, torch.Tensor] | None = None) -> None:
    """Rank 0: broadcast a message {kind, meta (JSON), tensors} to every other rank."""
    global _last_message
    tensors = {name: t.detach().cpu().contiguous() for name, t in (tensors or {}).items()}
    layout, offset = [], 0
    for name, t in tensors.items():
        nbytes = t.numel() * t.element_size()
        layout.append([name, str(t.dtype).removeprefix("torch."), list(t.shape), offset, nbytes])
        offset += nbytes
    header = json.dumps({"kind": kind, "meta": meta or {}, "tensors": layout}).encode()
    blob = torch.cat([t.reshape(-1).view(torch.uint8) for t in tensors.values()]) if tensors \
        else torch.empty(0, dtype=torch.uint8)
    _last_message = (torch.tensor([len(header), blob.numel()], dtype=torch.int64),
                     torch.frombuffer(bytearray(header), dtype=torch.uint8), blob)
    with _collective(_current, f"sending '{kind}' to the other ranks", None):
        for part in _last_message:
            if part.numel():   # the sizes and the header never empty; the tensors' bytes may be
                dist.broadcast(part, 0)


def receive() -> tuple[str, dict, dict[str, torch.Tensor]]:
    """The other ranks: wait for rank 0's next message; (kind, meta, tensors)."""
    global _last_message
    sizes = torch.empty(2, dtype=torch.int64)
    with _collective(_current, "waiting for rank 0", None):
        dist.broadcast(sizes, 0)
        header_bytes = torch.empty(int(sizes[0]), dtype=torch.uint8)
        dist.broadcast(header_bytes, 0)
        blob = torch.empty(int(sizes[1]), dtype=torch.uint8)
        if blob.numel():
            dist.broadcast(blob, 0)
    _last_message = (sizes, header_bytes, blob)
    header = json.loads(bytes(header_bytes.tolist()).decode())
    tensors = {name: blob[offset:offset + nbytes].clone().view(getattr(torch, dtype)).reshape(shape)
               for name, dtype, shape, offset, nbytes in header["tensors"]}
    return header["kind"], header["meta"], tensors


# --- per-step collectives ---------------------------------------------------------------------

class StepSync:
    """The trainer's hooks. With one rank every hook is the identity (the loop is unchanged)."""

    def __init__(self, world: World | None, reductions: dict[str, str]):
        self.world = world or World()
        self.rank, self.size = self.world.rank, self.world.size
        self.reductions = reductions  # accumulator name -> "sum" (the only kind the strategies have)
        self.pending: dict[str, torch.Tensor] = {}

    def share(self, views: Sequence[int]) -> Sequence[int]:
        """This rank's views of the step: every size-th one, from its rank on."""
        return views if self.size == 1 else views[self.rank::self.size]

    def gather_into(self, accumulators: dict[str, torch.Tensor], active: bool) -> dict[str, torch.Tensor]:
        """Where the strategy accumulates this step: the running accumulators themselves with one
        rank; otherwise fresh zeros, this step's increments, added in after the reduce."""
        if self.size == 1 or not active:
            self.pending = {}
            return accumulators
        unsummed = [name for name in accumulators if self.reductions.get(name) != "sum"]
        if unsummed:  # a running maximum would need a second, MAX, all-reduce of its increments
            raise ValueError(f"accumulators {unsummed} are not declared sums (strategy REDUCTIONS)")
        self.pending = {name: torch.zeros_like(t) for name, t in accumulators.items()}
        return self.pending

    def reduce(self, params: dict[str, torch.Tensor], accumulators: dict[str, torch.Tensor],
               loss_sum: torch.Tensor, psnr_sum: torch.Tensor, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """All-reduce the step's gradients, accumulator increments and loss/PSNR sums (one flat
        SUM buffer, in the parameters' dtype); returns the batch's loss and PSNR sums as float64
        tensors on the device (nothing is read back: the trainer reads them every log_every steps)."""
        if self.size == 1:
            return loss_sum, psnr_sum
        first = next(iter(params.values()))
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params.values()]
        sums = list(self.pending)
        parts = grads + [self.pending[n].to(first.dtype) for n in sums]
        parts.append(torch.stack([loss_sum, psnr_sum]).to(device=first.device, dtype=first.dtype))
        flat = torch.cat([t.reshape(-1) for t in parts])
        clock = time.perf_counter()
        with _collective(self.world, "the gradient all-reduce", step):
            dist.all_reduce(flat, op=dist.ReduceOp.SUM, group=self.world.group)
        self.world.stats["reduce_seconds"] += time.perf_counter() - clock
        self.world.stats["reduce_bytes"] += flat.numel() * flat.element_size()
        self.world.stats["steps"] += 1
        chunks = iter(torch.split(flat, [t.numel() for t in parts]))
        for p, grad in zip(params.values(), chunks):
            p.grad = grad.view_as(p).clone()
        for name in sums:
            accumulators[name] += next(chunks).view_as(accumulators[name]).to(accumulators[name].dtype)
        sums = next(chunks).double()
        return sums[0], sums[1]

    def check(self, params: dict[str, torch.Tensor], step: int, first: bool = False) -> None:
        """Every world.check_every steps (and at the first step): the ranks' parameter checksums
        must be equal, bit for bit (every rank applied the same update to the same values)."""
        every = self.world.check_every
        if self.size == 1 or not (first or (every and step % every == 0)):
            return
        mine = checksum(params)
        rows = [torch.empty_like(mine) for _ in range(self.size)]
        with _collective(self.world, "the parameter checksum", step):
            dist.all_gather(rows, mine, group=self.world.group)
        compare_checksums([row.cpu() for row in rows], list(params), step)


def checksum(params: dict[str, torch.Tensor]) -> torch.Tensor:
    """A few float64 numbers per parameter tensor: its row count, sum and sum of squares."""
    values = []
    for p in params.values():
        x = p.detach().double()
        values += [float(x.shape[0]), x.sum(), (x * x).sum()]
    return torch.stack([torch.as_tensor(v, dtype=torch.float64, device=p.device) for v in values])


def compare_checksums(rows: Sequence[torch.Tensor], names: Sequence[str], step: int) -> None:
    """Raise a RadfieldError naming the ranks whose checksum differs from rank 0's."""
    differ = [rank for rank, row in enumerate(rows) if not torch.equal(row, rows[0])]
    if not differ:
        return
    row = rows[differ[0]]
    tensors = sorted({names[k // 3] for k in range(len(row)) if row[k] != rows[0][k]})
    raise RadfieldError(f"the ranks' models diverged at step {step}: the parameter checksums of rank"
                        f"{'s' if len(differ) > 1 else ''} {', '.join(map(str, differ))} differ from rank 0's "
                        f"(in {', '.join(tensors)}); the ranks no longer apply the same update (different "
                        f"hardware or library builds?)")


@contextlib.contextmanager
def _collective(world: World, what: str, step: int | None) -> Iterator[None]:
    """A failed collective as one DistributedFailure line."""
    try:
        yield
    except (RuntimeError, ValueError) as error:
        at = f" at step {step}" if step is not None else ""
        raise DistributedFailure(f"rank {world.rank}: {what}{at} failed: another rank stopped or did not answer "
                                 f"within its timeout ({_first_line(error)}); {RESUME_HINT}") from None


def _first_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return text[0][:200] if text else type(error).__name__
