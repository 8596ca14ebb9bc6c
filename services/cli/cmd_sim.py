"""``gausslite sim [--dataset PATH] --out DIR``: local two-agent simulation (parser + fusion server + two
agents as separate processes on 127.0.0.1, configured like ``deploy/docker-compose.yml``), then concat /
vote / vote+refine fusion, evaluation and ``DIR/report.json`` + ``DIR/report.md`` (paper Sec. III-E, IV).
Without ``--dataset`` the synthetic default scene is generated into ``DIR/scene``.

Also registers the agent options of ``gausslite serve agent`` (``--agent-id --parser --fusion --dataset
--task --task-id --data-dir --annotations --set``): ``cmd_serve`` owns the generic serve options; the
agent-specific ones are added to its sub-parser here (this module is registered after it) and are
exported to the agent's environment variables (``GAUSSLITE_AGENT_ID``, ``GAUSSLITE_PARSER_ADDR``,
``GAUSSLITE_FUSION_ADDR``, ``GAUSSLITE_AGENT_DATASET``, ``GAUSSLITE_AGENT_TASK``,
``GAUSSLITE_AGENT_TASK_ID``, ``GAUSSLITE_DATA_DIR``, ``GAUSSLITE_AGENT_ANNOTATIONS``,
``GAUSSLITE_AGENT_SET``), which are also the documented fallbacks. gRPC is imported lazily.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from gausslite.core.environment import EnvironmentSettings

#: serve-agent flag → (argparse dest, environment variable, help)
AGENT_FLAGS = {
    "--agent-id": ("agent_id", "GAUSSLITE_AGENT_ID", "agent id on the fusion server (agent only)"),
    "--parser": ("parser_addr", "GAUSSLITE_PARSER_ADDR", "parser service host:port; empty = in-process rules (agent)"),
    "--fusion": ("fusion_addr", "GAUSSLITE_FUSION_ADDR", "fusion server host:port; empty = no pushes (agent)"),
    "--dataset": ("agent_dataset", "GAUSSLITE_AGENT_DATASET", "auto-start a replay mission of this dataset (agent)"),
    "--task": ("agent_task", "GAUSSLITE_AGENT_TASK", "task text of the auto-started mission (agent)"),
    "--task-id": ("agent_task_id", "GAUSSLITE_AGENT_TASK_ID", "task id in tasks.json (GT relevance/eval) (agent)"),
    "--data-dir": ("data_dir", "GAUSSLITE_DATA_DIR",
                   "persistent data folder: fusion, its store (the SQLite database fusion.sqlite3 with every subset, "
                   "keyframe and fused map it acknowledged; default ./gausslite_fusion_data; not used when "
                   "GAUSSLITE_FUSION_STORE names PostgreSQL); agent, its results (map.ply + summary.json)"),
    "--annotations": ("agent_annotations", "GAUSSLITE_AGENT_ANNOTATIONS",
                      "scene folder with objects.json/tasks.json for streamed missions (agent)"),
    "--data-roots": ("agent_data_roots", "GAUSSLITE_AGENT_DATA_ROOTS",
                     "comma-separated folders a StartMission's dataset/annotations path may lie in (agent)"),
}


def register(subparsers) -> None:
    """Add the ``sim`` subcommand, and the agent options of ``serve`` (when registered)."""
    p = subparsers.add_parser("sim", help="local two-agent simulation with fusion and a report",
                              description=__doc__.split("\n\n")[0],
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", default=None,
                   help="scene folder or ROS bag with objects.json/tasks.json beside it (default: generate the "
                        "synthetic scene)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", default=None, help="GaussLite YAML of site settings (default: none, the measured defaults)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override, e.g. mapper.iters_per_frame=5 agent.max_frames=4 sim.scene.frames=6")
    p.add_argument("--tasks", default=None, help="two task ids, comma-separated (agent_a,agent_b)")
    p.add_argument("--iters", type=int, default=None, help="shortcut for mapper.iters_per_frame")
    p.add_argument("--seeds-per-frame", dest="seeds_per_frame", type=int, default=None,
                   help="shortcut for mapper.seeding.seeds_per_frame")
    p.add_argument("--downscale", type=float, default=None, help="shortcut for agent.downscale")
    p.add_argument("--max-frames", type=int, default=None, help="shortcut for agent.max_frames")
    # Options of the report machinery and the benchmarks work but are not listed by --help (SUPPRESS):
    # --protocols: the scoring protocols of the own and fused maps, sensor (always), keyframes, novel, tracked,
    # novel-tracked (every 10th frame withheld from the agents; agent.scoring.protocols; default all, docs/realtime.md)
    p.add_argument("--protocols", default=None, metavar="P[,P...]", help=argparse.SUPPRESS)
    p.add_argument("--realtime", action="store_true",
                   help="agents replay at the dataset's clock through keyframe ingest (agent.realtime=true), as a "
                        "robot streams; the report adds frames received/keyframed/skipped, latencies and the ROI "
                        "PSNR over every frame")
    p.add_argument("--rate", type=float, default=None, help="with --realtime: clock speed-up (agent.rate, default 1)")
    p.add_argument("--fps", type=float, default=None,
                   help="with --realtime: clock of Replica / 7-Scenes replays, frame index / fps (agent.fps; default 30)")
    p.add_argument("--budget", type=float, default=None,
                   help="seconds per mapped keyframe (mapper.keyframe_budget_s; --realtime default 1.0, otherwise "
                        "the fixed iterations of mapper.iters_per_frame)")
    # --baseline uniform (not listed): also run matched uniform agents (the same sim with mapper.mode=uniform, into
    # OUT/baseline_uniform) and put their own-map ROI PSNR beside GaussLite's in report.md (what the task buys)
    p.add_argument("--baseline", choices=("uniform",), default=None, help=argparse.SUPPRESS)
    p.add_argument("--offline-report", default=None, metavar="DIR",
                   help="an earlier `gausslite sim` (every frame, same dataset) whose agents' ROI PSNR goes next to "
                        "the realtime figures in report.md")
    # --report-only (not listed): with --offline-report, add the offline column to the finished realtime run in --out
    # (rewrites its report.json/report.md, runs nothing)
    p.add_argument("--report-only", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--timeout", type=float, default=None, help="overall bound in seconds (default sim.timeout_s)")
    p.add_argument("--token", default=None, help="bearer token for all services (env GAUSSLITE_TOKEN)")
    p.add_argument("--fusion-token", default=None,
                   help="this client's own token for the fusion server when it checks per-agent tokens "
                        "(env GAUSSLITE_FUSION_TOKEN, or the file GAUSSLITE_FUSION_TOKEN_FILE; default --token)")
    p.add_argument("--attach", default=None, metavar="NAME=HOST:PORT,...",
                   help="drive running services instead of starting processes (parser=..,fusion_server=..,"
                        "agent_a=..,agent_b=..; the compose 'report' service uses this)")
    # with --attach: the same TLS options as every client
    from gausslite_services.common.cli_options import add_client_credential_arguments
    add_client_credential_arguments(p, token=False, server="an attached service")
    # lazy: the command line starts without loading the services or gRPC
    from gausslite.cli.cmd_map import add_bag_args

    add_bag_args(p)  # shortcuts for agent.bag.<field>
    # --context-report REPORT_JSON (not listed): report.json of the same sim run with --set mapper.roi_render=context,
    # adds each agent's own_roi_psnr_context; --merge-only (not listed): with --context-report, into the existing
    # DIR/report.json (rewrites DIR/report.* only, no new run)
    p.add_argument("--context-report", default=None, metavar="REPORT_JSON", help=argparse.SUPPRESS)
    p.add_argument("--merge-only", action="store_true", help=argparse.SUPPRESS)
    p.set_defaults(func=_handle)
    _extend_serve(subparsers)


def _extend_serve(subparsers) -> None:
    serve = getattr(subparsers, "choices", {}).get("serve")
    if serve is None:
        return
    group = serve.add_argument_group("agent options (gausslite serve agent; --data-dir also fusion)")
    existing = serve._option_string_actions  # options another module already added are reused
    for flag, (dest, _env, help_) in AGENT_FLAGS.items():
        if flag not in existing:
            group.add_argument(flag, dest=dest, default=None, help=f"{help_} (env {_env})")
    if "--set" not in existing:
        group.add_argument("--set", dest="config_overrides", action="append", default=None, metavar="KEY=VALUE",
                           help="configuration override (repeatable): agent.* and mapper.* for an agent (env "
                                "GAUSSLITE_AGENT_SET), fusion.* for the fusion server (env GAUSSLITE_FUSION_SET); "
                                "';'-separated in the environment")
    original = serve.get_default("func")

    def handle(args: argparse.Namespace) -> int:
        if getattr(args, "service", None) == "parser" and getattr(args, "config_overrides", None):
            print("gausslite serve parser: error: --set applies to the agent and fusion services", file=sys.stderr)
            return 2
        if getattr(args, "service", None) == "agent":
            export_agent_env(args, os.environ, serve)
        elif getattr(args, "data_dir", None):  # --data-dir is generic (fusion store, agent results)
            os.environ["GAUSSLITE_DATA_DIR"] = str(args.data_dir)
        return original(args)

    serve.set_defaults(func=handle)


def export_agent_env(args: argparse.Namespace, env, serve_parser=None) -> None:
    """Copy the given ``serve agent`` flags into their environment variables (flags win over env)."""
    for flag, (dest, var, _h) in AGENT_FLAGS.items():
        if serve_parser is not None and flag in serve_parser._option_string_actions:
            dest = serve_parser._option_string_actions[flag].dest
        val = getattr(args, dest, None)
        if val is not None:
            env[var] = str(val)
    ov = getattr(args, "config_overrides", None)
    if ov:
        env["GAUSSLITE_AGENT_SET"] = ";".join(ov)


def _report_only(args: argparse.Namespace) -> int:
    """``--report-only``: attach ``--offline-report`` to the finished realtime run in ``--out`` (nothing re-run)."""
    if not args.offline_report:
        print("gausslite sim: error: --report-only needs --offline-report", file=sys.stderr)
        return 2
    # lazy: the command line starts without loading the library's scoring
    from gausslite.team import attach_offline_report

    try:
        report = attach_offline_report(args.out, args.offline_report)
    except (ValueError, OSError) as e:
        print(f"gausslite sim: error: {e}", file=sys.stderr)
        return 1
    _print_answer(report)
    return 0


def _handle(args: argparse.Namespace) -> int:
    if args.report_only:
        return _report_only(args)
    overrides = list(args.overrides)
    for flag, key in (("iters", "mapper.iters_per_frame"), ("seeds_per_frame", "mapper.seeding.seeds_per_frame"),
                      ("downscale", "agent.downscale"), ("max_frames", "agent.max_frames")):
        if getattr(args, flag) is not None:
            overrides.append(f"{key}={getattr(args, flag)}")
    if args.protocols is not None:
        protos = [q.strip() for q in args.protocols.split(",") if q.strip()]
        known = ("sensor", "keyframes", "novel", "tracked", "novel-tracked")
        if not protos or any(q not in known for q in protos):
            print(f"gausslite sim: error: --protocols {args.protocols!r}: choose among {', '.join(known)}",
                  file=sys.stderr)
            return 2
        overrides.append(f"agent.scoring.protocols=[{', '.join(protos)}]")
    # lazy: the command line starts without loading the services or gRPC
    from gausslite.cli.cmd_map import bag_options_from_args

    overrides += [f"agent.bag.{k}={v}" for k, v in bag_options_from_args(args).items()]
    if args.iters is not None and not any(o.startswith("mapper.warmup_iters=") for o in overrides):
        overrides.append(f"mapper.warmup_iters={max(0, args.iters // 3)}")
    if (args.rate is not None or args.fps is not None) and not args.realtime:
        print("gausslite sim: error: --rate and --fps need --realtime", file=sys.stderr)
        return 2
    if args.realtime:
        overrides.append("agent.realtime=true")
        for flag, key in (("rate", "agent.rate"), ("fps", "agent.fps")):
            if getattr(args, flag) is not None:
                overrides.append(f"{key}={getattr(args, flag)}")
        if args.budget is None and not any(o.startswith("mapper.keyframe_budget_s=") for o in overrides):
            overrides.append("mapper.keyframe_budget_s=1.0")
    if args.budget is not None:
        overrides.append(f"mapper.keyframe_budget_s={args.budget}")
    tasks = [t.strip() for t in args.tasks.split(",")] if args.tasks else None
    try:
        variables = EnvironmentSettings.read()
    except ValueError as e:
        print(f"gausslite sim: error: {e}", file=sys.stderr)
        return 2
    attach = None
    if args.attach:
        try:
            attach = dict(item.split("=", 1) for item in args.attach.split(",") if item.strip())
        except ValueError:
            print("gausslite sim: error: --attach must look like name=host:port,...", file=sys.stderr)
            return 2
        missing = {"parser", "fusion_server", "agent_a", "agent_b"} - set(attach)
        if missing - {"parser"}:
            print(f"gausslite sim: error: --attach misses {sorted(missing)}", file=sys.stderr)
            return 2
        tls = [args.tls_ca or variables.tls_ca, args.tls_client_cert or variables.tls_client_cert,
               args.tls_client_key or variables.tls_client_key]
        if any(tls):  # the attached services run TLS: every client of this run uses it
            # lazy: the command line starts without loading the services or gRPC
            from gausslite_services.common.client_tls import client_tls_from_files, set_default_client_tls

            try:
                set_default_client_tls(*client_tls_from_files(*tls))
            except (OSError, ValueError) as e:
                print(f"gausslite sim: error: TLS options: {e}", file=sys.stderr)
                return 2
    elif args.tls_ca or args.tls_client_cert or args.tls_client_key:
        print("gausslite sim: error: --tls-* apply to --attach (the local services run on loopback)", file=sys.stderr)
        return 2
    if args.baseline and args.attach:
        print("gausslite sim: error: --baseline starts its own uniform agents; it cannot drive --attach services",
              file=sys.stderr)
        return 2
    if args.merge_only:
        return _merge_context(args)
    try:
        # lazy: the command line starts without loading the services or gRPC
        from gausslite_services.common.auth import read_secret
        from gausslite_services.sim import run_sim

        fusion_token = args.fusion_token or variables.fusion_token or (
            read_secret(variables.fusion_token_file) if variables.fusion_token_file else None)
        res = run_sim(args.out, args.dataset, config=args.config, overrides=overrides, task_ids=tasks, attach=attach,
                      offline_report=args.offline_report,
                      timeout_s=args.timeout, token=args.token or variables.token,
                      fusion_token=fusion_token, context_report=args.context_report)
        if args.baseline:
            res = _run_baseline(args, res, overrides, tasks, attach)
    except KeyboardInterrupt:
        print("gausslite sim: interrupted (all services stopped)", file=sys.stderr)
        return 130
    except (ValueError, KeyError, OSError, RuntimeError, TimeoutError) as e:
        print(f"gausslite sim: error: {e}", file=sys.stderr)
        return 1
    _print_answer(res.report)
    print(f"wrote {res.out / 'report.json'} and {res.out / 'report.md'} (every protocol and map, the pushes, the "
          f"renders) in {res.seconds:.0f} s")
    return 0


def _print_answer(report: dict) -> None:
    """Print the first screen of a simulation's report (``answer_markdown``); ``report.md`` holds the rest."""
    # lazy: the command line starts without loading the library's scoring
    from gausslite.team import answer_markdown

    print(answer_markdown(report))


def _run_baseline(args: argparse.Namespace, res, overrides: list, tasks, attach):
    """``--baseline uniform``: the same sim with ``mapper.mode=uniform`` into ``OUT/baseline_uniform`` (run after the
    GaussLite one, never beside it: live budgets are wall time), then its agents' figures into the main report."""
    # lazy: the command line starts without loading the services or gRPC
    import json

    from gausslite.team import attach_uniform_baseline, write_markdown
    from gausslite_services.sim import run_sim

    base = run_sim(res.out / "baseline_uniform", args.dataset, config=args.config,
                   overrides=[*overrides, "mapper.mode=uniform"], task_ids=tasks, attach=attach,
                   timeout_s=args.timeout, token=args.token or EnvironmentSettings.read().token)
    attach_uniform_baseline(res.report, base.report)
    (res.out / "report.json").write_text(json.dumps(res.report, indent=2))
    write_markdown(res.report, res.out / "report.md")
    return res


def _merge_context(args: argparse.Namespace) -> int:
    """``--merge-only``: add the context run's figures to an existing report (no processes)."""
    # lazy: the command line starts without loading the services or gRPC
    import json
    from pathlib import Path

    from gausslite.team import attach_context_baseline, plot_pushes, write_markdown

    out = Path(args.out)
    if not args.context_report:
        print("gausslite sim: error: --merge-only needs --context-report", file=sys.stderr)
        return 2
    try:
        report = json.loads((out / "report.json").read_text())
        attach_context_baseline(report, json.loads(Path(args.context_report).read_text()))
    except (OSError, ValueError, KeyError) as e:
        print(f"gausslite sim: error: {e}", file=sys.stderr)
        return 1
    if plot_pushes(report, out / "pushes.png"):
        report["pushes_plot"] = "pushes.png"
    (out / "report.json").write_text(json.dumps(report, indent=2))
    write_markdown(report, out / "report.md")
    _print_answer(report)
    return 0
