"""A dataset to disk: :func:`generate_dataset` (resumable, deterministic, sharded; one process
or a pool of them, :mod:`dope_hope.synth.pool`).

Frame ``i`` of a dataset with seed ``S`` depends only on (S, i), the inputs and the config:
its random streams come from ``np.random.SeedSequence([S, i])`` (see scene.frame_streams).
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from dope_hope.errors import ConfigError
from dope_hope.synth.generate import FrameGenerator, SynthJob
from dope_hope.synth.pool import render_in_pool
from dope_hope.synth.preview import write_preview
from dope_hope.synth.settings import parse_shard
from dope_hope.synth.writer import check_or_write_info, is_complete, remove_stale_frame_temporaries


@dataclass
class GenerateSummary:
    """What :func:`generate_dataset` did."""

    out_dir: Path
    written: int
    skipped: int
    seconds: float
    preview: Path | None = None

    @property
    def frames_per_s(self) -> float:
        return self.written / self.seconds if self.seconds > 0 else 0.0


def generate_dataset(out_dir: str | os.PathLike, job: SynthJob, count: int, workers: int = 1,
                     shard: tuple[int, int] | str | None = None, preview: bool = False,
                     progress: bool = True, indices: list[int] | None = None,
                     on_frame: Callable[[int], None] | None = None) -> GenerateSummary:
    """Generate frames 0..count-1 (those of this shard) of ``job`` into ``out_dir``.

    Frames whose JSON exists are skipped (resume). With ``workers`` > 1, frames are rendered
    by that many spawned processes, each with its own renderer; the frames are identical to
    a single-process run. ``shard`` = (i, n) renders the frames with ``index % n == i``.

    Args:
        indices: explicit frame indices instead of range(count) (still filtered by shard).
        on_frame: called with each frame index once it is written (in this process).
        preview: also write ``preview.png`` (:func:`write_preview`).

    Returns:
        A GenerateSummary (frames written / skipped, seconds, preview path).
    """
    if count < 0:
        raise ConfigError(f"--count must be >= 0, got {count}")
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    i_shard, n_shard = parse_shard(shard)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    gen_kwargs = job.generator_kwargs()
    # Validate inputs in this process (clear errors before any worker starts).
    local = FrameGenerator(**gen_kwargs)
    check_or_write_info(out, local.dataset_info(gen_kwargs))
    wanted = [i for i in (range(count) if indices is None else indices) if i % n_shard == i_shard]
    todo = [i for i in wanted if not is_complete(out, i)]
    remove_stale_frame_temporaries(out, set(todo))
    start = time.perf_counter()
    bar = tqdm(total=len(todo), unit="frame", desc="synth", disable=not progress, dynamic_ncols=True)

    def done(i: int) -> None:
        bar.update(1)
        if on_frame is not None:
            on_frame(i)

    try:
        if workers == 1 or len(todo) <= 1:
            for i in todo:
                local.write_frame(out, i)
                done(i)
        else:
            render_in_pool(gen_kwargs, out, todo, workers, done)
    finally:
        bar.close()
        local.close()
    seconds = time.perf_counter() - start
    preview_path = write_preview(out, wanted, int(local.cfg.output.preview_frames)) if preview else None
    return GenerateSummary(out, len(todo), len(wanted) - len(todo), seconds, preview_path)
