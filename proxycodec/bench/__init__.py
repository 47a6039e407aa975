"""The size / quality / time trade-off benchmark, shared by ``proxycodec bench`` and ``benchmarks/tradeoff.py``.

Every measured step (fit, encode, decode + evaluation, SPZ conversion) runs in its own Python subprocess
(``python -m proxycodec.bench --worker JSON``), so its peak RSS (``getrusage(RUSAGE_SELF).ru_maxrss`` of that process,
plus ``RUSAGE_CHILDREN`` for the Node.js converter) is its own. Steps are recorded in ``results.json`` as soon as they
finish (written atomically), keyed by a step id and its arguments: a re-run skips every step already done with the
same arguments (and whose output files still exist), so an interrupted run resumes where it stopped.

A *point* is one way of storing a scene: a container from some encode settings, the uncompressed anchor PLY + weights,
a plain 3DGS INRIA PLY or its SPZ conversion. Per point: bytes on disk, PSNR / SSIM averaged over the ten resolutions
10%..100% (on the first ``views`` test views), PSNR at 10% and 100%, fit / encode / decode seconds, mean render time
per resolution, peak RSS per step. Encodes that decode to the same scene (they differ only in the zstd level, the
entropy coding or the position coding: ``steps._content_key``) share one quality evaluation (``quality_from``);
their decode is still timed on its own.

Modules: ``steps`` (the measured steps), ``runner`` (runs and records them; the subprocess worker), ``sweeps``
(points, the encode sweeps, ``proxycodec bench``), ``report`` (Pareto fronts, markdown, plots).
"""

from .report import closing_notes, mark_pareto, markdown_report, pareto_front, plot_report, point_row, write_report
from .runner import Runner, machine_info, versions
from .steps import SPZ_TOOL, STEPS, run_worker
from .sweeps import (EvalSpec, encode_point, encode_sweep_plan, eval_step, knob_id, make_point, run_bench,
                     run_encode_sweeps)

__all__ = [
    "EvalSpec", "Runner", "SPZ_TOOL", "STEPS", "closing_notes", "encode_point", "encode_sweep_plan", "eval_step",
    "knob_id", "machine_info", "make_point", "mark_pareto", "markdown_report", "pareto_front", "plot_report",
    "point_row", "run_bench", "run_encode_sweeps", "run_worker", "versions", "write_report",
]
