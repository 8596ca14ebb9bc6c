"""The paper's real-time protocol as a benchmark: live single agents, a per-keyframe time budget, a matched
Gaussian cap, no final pass (paper Sec. IV-A, Baselines). See ``docs/realtime.md``.

    python -m bench.realtime [--scenes tum_fr1_rpy,synthetic_circle,room0] [--budgets 0.25,0.5,1,2]
                             [--runs 3] [--modes uniform,gausslite] [--clock scaled|dataset]
                             [--final-pass-budgets 0.5] [--score-at mapping|scene] [--set KEY=VALUE ...]
                             [--out bench/results/realtime.json] [--allow-failed]

Each run is one agent mission (:class:`gausslite.mission.AgentRuntime`, in process, no fusion server)
that replays the scene through the agent's keyframe ingest as a robot streams it: frames arrive at the
scene's clock, the keyframe selector keeps the newest candidate while the mapper is busy, and every mapped
keyframe gets ``budget`` seconds of wall time (decoding, relevance and seeding included). Both modes map with
the agent's default settings (the measured ones) and the scene's sensor profile, at the same
**binding** Gaussian cap (``mapper.budget.max_gaussians``; each run's final count is reported), the same keyframe
rule, no sharing and **no final pass**. At the end of the mission the map is scored over **every** frame of
the sequence (skipped ones included): ROI PSNR, PSNR, SSIM. With ``--final-pass-budgets`` the same map then
gets the profile's final pass and is scored again (a separate column).

Clock. ``--clock scaled`` (default) replays at ``rate = 0.5 / budget``: every budget covers the same 0.5 s of
the sequence per keyframe, so 2 s per keyframe is 4× the compute of 0.5 s, as a robot whose computer is 4×
faster (the paper adjusts the frame step to the budget). The 0.5 s budget is the dataset clock itself.
``--clock dataset`` replays every budget at the dataset clock (the same total compute; the budget only trades
keyframes against iterations).

Runs are wall-clock measurements: they run one at a time in this process, and nothing else should run
beside the bench. Writes ``bench/results/realtime.json`` (``{"scenes": {scene: {"cap", "budgets": {b:
{"uniform": {...}, "gausslite": {...}, "gain", "gain_ci", "gain_interval", "gain_std", "protocols"}}}}, "runs":
[...]}``), ``realtime.md`` and ``realtime_<scene>.png`` (ROI PSNR against budget, both modes). After each run the
runs so far go to ``<out>.partial.json``; ``--resume`` continues from it.

Scoring resolution. ``--score-at mapping`` (default) scores each map at the resolution its mission mapped at;
``--score-at scene`` at the scene's own (the dataset as the scene spec loads it, e.g. TUM at 320×240), whatever
resolution the agent chose, so that runs mapped at different resolutions compare on the same pixels and a map's
finer detail counts (``bench.compute_sweep``). Each run records the basis and the size it was scored at.

Failed missions. Each run records how its mission ended: ``end_state`` (``FINISHED``, or ``FAILED`` when it stopped,
out of memory say), ``error`` (the status's ``last_error``, e.g. ``"mapping frame 612 failed: ..."``) and the status
counters ``frames_failed`` and ``corrections_rejected`` (:func:`bench._missions.mission_outcome`). A run whose mission
did not finish or failed to map frames is a failed run (:func:`bench._missions.failed`): it stays in
``runs`` with whatever it scored (or ``score_error``), is left out of every mean and gain (each budget block lists it
under ``failed_runs``, the result under its top-level ``failed_runs``), is marked † in the tables, and makes the
command exit 1 after writing its result unless ``--allow-failed``. ``--resume`` runs a failed mission again.

Gains pair GaussLite and uniform frame by frame within each run (the same seed), and only runs scored at the same
resolution (:func:`pairable_runs`); over several runs the interval is run-clustered, a t-interval over the
per-run gains (:func:`gausslite.stats.paired_gain`). Each run records the settings its mission ran with
(``"mission"``, :func:`mission_settings`). ``--reaggregate`` rewrites a written result's summary from its runs.

Modules: :mod:`~bench.realtime.scenes` (the scenes and their loading), :mod:`~bench.realtime.protocol` (scoring a
map under the protocols), :mod:`~bench.realtime.missions` (the live runs, the twin, calibration),
:mod:`~bench.realtime.summary` (means over runs, paired gains), :mod:`~bench.realtime.tables` (tables, plots) and
:mod:`~bench.realtime.cli` (the command line). The names below are this package's interface.
"""

from bench.realtime.cli import main, reaggregate
from bench.realtime.missions import (RESOLUTION_KEYS, agent_config, calibrate, first_choice, keyframe_schedule,
                                     load_average, mission_result, mission_settings, run_key, run_one,
                                     shared_resolution, start_mission, twin_one)
from bench.realtime.protocol import (TRACK_ITERS, TRACK_STRIDE, check_withheld, map_scores, novel_ids, save_render,
                                     score, score_deferred, training_frames)
from bench.realtime.scenes import (MODES, REFERENCE_BUDGET_S, RESULTS, SCENES, SHARED, Preloaded, dataset_scenes,
                                   load_scene, scene_path)
from bench.realtime.summary import budget_key, mapping_resolution, pairable_runs, summarise
from bench.realtime.tables import failed_mark, gain_cell, plot_scene, protocol_table, table

__all__ = ["MODES", "REFERENCE_BUDGET_S", "RESOLUTION_KEYS", "RESULTS", "SCENES", "SHARED", "TRACK_ITERS",
           "TRACK_STRIDE", "Preloaded", "first_choice", "shared_resolution",
           "agent_config", "budget_key", "calibrate", "check_withheld", "dataset_scenes", "failed_mark", "gain_cell",
           "keyframe_schedule", "load_average", "load_scene", "main", "map_scores", "mapping_resolution",
           "mission_result", "mission_settings", "novel_ids", "pairable_runs", "plot_scene", "protocol_table",
           "reaggregate", "run_key", "run_one", "save_render", "scene_path", "score", "score_deferred",
           "start_mission", "summarise", "table", "training_frames", "twin_one"]
