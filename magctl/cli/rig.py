"""``magctl rig serve-sim`` and ``magctl rig run``."""

from __future__ import annotations

import json
import sys
from functools import partial

from magctl.cli.common import (
    add_json,
    emit,
    existing_dir,
    existing_file,
    finite_float,
    nonneg_float,
    nonneg_int,
    output_dir,
    output_file,
    positive_float,
    positive_int,
    rig_address,
    seed,
)
from magctl.cli.rig_calibrate import add_parsers as add_calibrate_parsers
from magctl.core.errors import MagctlError


def register(sub) -> None:
    p = sub.add_parser("rig", help="simulated rig server and the 30 Hz rig runtime")
    rs = p.add_subparsers(dest="rig_command", metavar="RIG_COMMAND")
    rs.required = True
    add_calibrate_parsers(rs)

    s = rs.add_parser("serve-sim", help="serve a simulated rig (protocol v2, docs/rig-protocol.md)")
    s.add_argument("--bind", default="tcp://127.0.0.1:5555",
                   help="ZeroMQ endpoint (default tcp://127.0.0.1:5555); an address beyond loopback needs CURVE or "
                        "--insecure")
    s.add_argument("--spheres", type=nonneg_int, default=1, help="number of spheres in the scene (default 1)")
    s.add_argument("--plant", choices=("physics", "standin"), default="physics",
                   help="physics: the plant blocks (coils, stick-slip robot, Stokes-flow spheres, camera, Kalman "
                        "tracker; default); standin: the fast kinematic stand-in")
    s.add_argument("--robot-um", type=finite_float, nargs=2, metavar=("X", "Y"), default=None,
                   help="robot start position in µm (default models/rig.toml [scene], inside the camera field)")
    s.add_argument("--sphere-um", type=finite_float, nargs=2, metavar=("X", "Y"), action="append", default=None,
                   help="a sphere's position in µm (repeat per sphere; default: ahead of the robot every 1 mm)")
    s.add_argument("--blackout-s", type=nonneg_float, nargs=2, metavar=("T0", "T1"), default=None,
                   help="force tracking loss during [T0, T1) s (to exercise loss handling)")
    s.add_argument("--seed", type=seed, default=0, help="root seed (integer >= 0)")
    _server_options(s)
    s.set_defaults(func=cmd_serve_sim)

    c = rs.add_parser("serve", help="serve a lab rig built from the devices a lab file names (docs/bring-up.md)",
                      description="The rig server of a lab: the camera, tracker and coil driver of --config "
                                  "(lab.toml), behind the same protocol, sessions, limits and watchdog as serve-sim.")
    c.add_argument("--config", type=existing_file, required=True, metavar="LAB.toml",
                   help="the lab file (examples/lab-sim.toml runs the simulated devices)")
    c.add_argument("--bind", default="tcp://127.0.0.1:5555",
                   help="ZeroMQ endpoint (default tcp://127.0.0.1:5555); an address beyond loopback needs CURVE or "
                        "--insecure")
    c.add_argument("--dry-run", action="store_true",
                   help="check and log every command but keep the coils at zero (a first run with the coils off)")
    _server_options(c)
    c.set_defaults(func=cmd_serve)

    x = rs.add_parser("experiment", help="run the identification experiment (docs/identify.md), one log per run",
                      description="The excitation `magctl identify` needs, run on one rig in order: the open-loop "
                                  "speed sweep (task identify), front pushes of several lengths and side passes at "
                                  "a ladder of gaps (models/identify.toml [experiment]); each run logged like "
                                  "`magctl rig run --log`.")
    x.add_argument("--rig", type=rig_address, required=True,
                   help="rig server address (tcp://HOST:PORT) or 'sim' for an in-process simulated rig")
    x.add_argument("--out", type=output_dir, required=True, help="folder for the run logs (NN-name.jsonl)")
    x.add_argument("--spheres", type=positive_int, default=1, help="with --rig sim: number of spheres")
    x.add_argument("--plant", choices=("physics", "standin"), default="physics", help="with --rig sim: the plant")
    x.add_argument("--seed", type=seed, default=0, help="root seed (integer >= 0)")
    x.add_argument("--engine", choices=("auto", "compiled", "interpreted"), default="auto",
                   help="controller engine of every run")
    x.add_argument("--log-max-mb", type=positive_float, default=None, metavar="N",
                   help="largest part of each run log in MB (10^6 bytes), as for rig run (default models/rig.toml "
                        "[log] max_mb)")
    x.add_argument("--quiet", action="store_true")
    add_json(x)
    x.set_defaults(func=cmd_experiment)

    k = rs.add_parser("keys", help="generate CURVE key pairs for a server and a client")
    k.add_argument("--out", type=output_dir, required=True, help="folder for server.key(_secret), client.key(_secret), "
                                                            "clients/")
    add_json(k)
    k.set_defaults(func=cmd_keys)

    r = rs.add_parser("run", help="run a task on a rig at 30 Hz")
    r.add_argument("--rig", required=True, type=rig_address,
                   help="rig server address (tcp://HOST:PORT), 'sim' for an in-process simulated rig, or a lab file "
                        "(lab.toml) for an in-process rig of its devices")
    r.add_argument("--task", required=True,
                   help="task name: goto, front-push, side-push, assemble, front-side-assemble, patrol, identify "
                        "(the open-loop speed sweep for magctl identify)")
    r.add_argument("--target-um", type=finite_float, nargs=2, metavar=("X", "Y"), help="goto: target position in µm")
    r.add_argument("--goal-um", type=finite_float, nargs=2, metavar=("X", "Y"),
                   help="push tasks: goal of the sphere in µm")
    r.add_argument("--kc", type=finite_float, default=None, help="front-push: learning gain K_c (eq 13)")
    r.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="task option, e.g. push_speed_um_s=1000, ks=0.9, model=exp, servo=default (repeatable)")
    r.add_argument("--log", type=output_file, default=None, help="run log to create (JSON lines)")
    r.add_argument("--log-max-mb", type=positive_float, default=None, metavar="N",
                   help="largest part of the run log in MB (10^6 bytes): past it the log goes on in LOG.1, "
                        "LOG.2… (magctl log reads them all from LOG; default models/rig.toml [log] max_mb)")
    r.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds (> 0)")
    r.add_argument("--max-ticks", type=positive_int, default=None, help="stop after this many ticks (>= 1)")
    r.add_argument("--spheres", type=nonneg_int, default=1, help="with --rig sim: number of spheres")
    r.add_argument("--fast", action="store_true",
                   help="ticks back to back in simulated time, not at 30 Hz: with --rig sim, a simulated lab file or a "
                        "--lockstep server")
    r.add_argument("--plant", choices=("physics", "standin"), default="physics",
                   help="with --rig sim: the plant blocks (default) or the fast kinematic stand-in")
    r.add_argument("--rt-priority", type=positive_int, default=None, metavar="P",
                   help="run the loop under SCHED_FIFO priority P (Linux, needs CAP_SYS_NICE)")
    r.add_argument("--reset", action="store_true", help="ask a simulated rig server to restart its scene")
    r.add_argument("--takeover", action="store_true",
                   help="take the rig over from another client's live session (the server logs it)")
    r.add_argument("--curve-server-key", type=existing_file, default=None, metavar="FILE",
                   help="the server's public key (server.key): connect with CURVE; needs --curve-secret")
    r.add_argument("--curve-secret", type=existing_file, default=None, metavar="FILE",
                   help="this client's secret key (client.key_secret from 'magctl rig keys')")
    r.add_argument("--seed", type=seed, default=0, help="root seed (integer >= 0)")
    r.add_argument("--engine", choices=("auto", "compiled", "interpreted"), default="auto",
                   help="controller engine: one compiled call per frame (auto: when every block has a kernel; "
                        "compiled before the coils are activated) or the interpreted blocks")
    r.add_argument("--view", nargs="?", const="127.0.0.1:8050", default=None, metavar="HOST:PORT",
                   help="serve the live page of the run (default 127.0.0.1:8050; port 0: any free port; needs "
                        "magctl[view])")
    r.add_argument("--view-controls", action="store_true",
                   help="with --view: the page's stop and pause buttons act on the run (beyond loopback they need "
                        "the token the printed address carries)")
    r.add_argument("--quiet", action="store_true")
    add_json(r)
    r.set_defaults(func=cmd_run, parser=r)


def _scene(args):
    import numpy as np

    from magctl.config import load_model
    from magctl.rig.plant import Scene

    params = load_model("rig")
    if args.sphere_um:
        if len(args.sphere_um) != args.spheres and args.spheres != 1:
            raise MagctlError(f"--spheres {args.spheres} but {len(args.sphere_um)} --sphere-um given")
        scene = Scene(robot=Scene.default(0, params).robot, spheres=np.asarray(args.sphere_um, dtype=float) * 1e-6)
    else:
        scene = Scene.default(args.spheres, params)
    if args.robot_um:
        shift = np.asarray(args.robot_um, dtype=float) * 1e-6 - scene.robot
        scene.robot = scene.robot + shift
        if not args.sphere_um:  # default spheres keep their place ahead of the robot
            scene.spheres = scene.spheres + shift
    if args.blackout_s:
        scene.blackout = tuple(args.blackout_s)
    return scene, params


def _server_options(p) -> None:
    """The options every rig server takes: scheduling, lock-step, security."""
    p.add_argument("--rt-priority", type=positive_int, default=None, metavar="P",
                   help="run under SCHED_FIFO priority P (Linux, needs CAP_SYS_NICE)")
    p.add_argument("--lockstep", action="store_true",
                   help="step one frame per 'read' (simulated time, deterministic) instead of at 30 Hz")
    p.add_argument("--curve-secret", type=existing_file, default=None, metavar="FILE",
                   help="server secret key (server.key_secret from 'magctl rig keys'): CURVE encryption and "
                        "client authentication; needs --curve-clients")
    p.add_argument("--curve-clients", type=existing_dir, default=None, metavar="DIR",
                   help="folder of the public keys (*.key) of the clients allowed to connect")
    p.add_argument("--allow", action="append", default=[], metavar="ADDR",
                   help="only peers at this IP address, in this network (10.1.0.0/16) or at this host name "
                        "(resolved at start; localhost) may connect (repeatable; default: any)")
    p.add_argument("--insecure", action="store_true",
                   help="allow --bind beyond loopback without CURVE (session tokens and commands travel in clear)")


def _check_curve(args, who: str) -> None:
    if (args.curve_secret is None) != (args.curve_clients is None):
        raise MagctlError(f"{who}: --curve-secret and --curve-clients go together")
    if args.curve_secret is None:
        return
    from magctl.rig.server import load_keypair

    try:
        _, secret = load_keypair(args.curve_secret)
    except (OSError, ValueError) as err:
        raise MagctlError(f"{who}: --curve-secret: {err}") from None
    if secret is None:
        raise MagctlError(f"{who}: --curve-secret {args.curve_secret}: no secret key in it (use server.key_secret)")
    if not args.curve_clients.is_dir() or not any(args.curve_clients.glob("*.key")):
        raise MagctlError(f"{who}: --curve-clients {args.curve_clients}: no client public keys (*.key)")


def _serve(args, who: str, station, limits, period: float, describe: dict, params) -> int:
    """Build the one rig server around ``station`` and serve until SIGTERM/SIGINT."""
    import zmq

    from magctl.rig.server import RigServer, announce

    try:
        server = RigServer(station, args.bind, limits, params.watchdog.timeout, period, describe, name=who,
                           lockstep=args.lockstep, session_timeout=params.session.timeout,
                           lockstep_wall_timeout=params.watchdog.lockstep_wall_timeout,
                           curve_secret=args.curve_secret, curve_clients=args.curve_clients, allow=args.allow,
                           insecure=args.insecure, takeover_interval=params.session.takeover_interval)
    except MagctlError as err:  # a bind beyond loopback without CURVE, an --allow entry that does not resolve
        raise MagctlError(f"{who}: {err}") from None
    try:
        return server.serve(ready=announce)
    except zmq.ZMQError as err:  # only binding raises: the serve loop catches everything else
        raise MagctlError(f"cannot serve on {args.bind}: {err}") from None


def cmd_serve(args) -> int:
    from magctl.config import load_model
    from magctl.rig.lab import build_station, load_lab
    from magctl.rig.runtime import set_realtime_priority

    cfg = load_lab(args.config)
    if args.lockstep and not cfg.simulated:
        raise MagctlError(f"rig serve: {args.config}: --lockstep (simulated time) needs the simulated devices")
    _check_curve(args, "rig serve")
    sched = set_realtime_priority(args.rt_priority)
    # the devices are opened once here, so that a missing one is an error before serving; the server reopens
    # them on every configure with reset
    build_station(cfg, lockstep=args.lockstep).close()
    station = partial(build_station, cfg, lockstep=args.lockstep, dry_run=args.dry_run)
    describe = {**cfg.describe(), "scheduling": sched, "lockstep": args.lockstep, "dry_run": args.dry_run}
    return _serve(args, "rig serve", station, cfg.limits, cfg.period, describe, load_model("rig"))


def cmd_serve_sim(args) -> int:
    from magctl.rig.interface import RigLimits
    from magctl.rig.plant import build_sim_plant
    from magctl.rig.runtime import set_realtime_priority
    from magctl.rig.sim import SimPlant

    scene, params = _scene(args)
    n = scene.spheres.shape[0]
    sched = set_realtime_priority(args.rt_priority)
    kind = {"physics": "physical plant blocks", "standin": "kinematic stand-in plant"}[args.plant]
    try:
        build_sim_plant(n, scene, params, plant=args.plant)  # a bad scene is an error before serving
    except MagctlError as err:
        raise MagctlError(f"serve-sim: {err}") from None
    _check_curve(args, "serve-sim")
    limits, period = RigLimits.from_params(params), 1.0 / params.runtime.rate
    station = partial(SimPlant, lambda: build_sim_plant(n, scene, params, plant=args.plant), limits, args.seed,
                      period)
    describe = {"kind": f"serve-sim ({kind})", "plant": args.plant, "scheduling": sched, "lockstep": args.lockstep,
                **scene.to_dict()}
    return _serve(args, "serve-sim", station, limits, period, describe, params)


def cmd_keys(args) -> int:
    from magctl.rig.server import generate_keys

    try:
        doc = generate_keys(args.out)
    except (OSError, FileExistsError) as err:
        raise MagctlError(f"rig keys: {err}") from None
    emit(args, doc, lambda d: "\n".join([
        f"server: {d['server_secret']} (secret, for serve-sim --curve-secret), {d['server_public']} (public, for "
        f"rig run --curve-server-key)",
        f"client: {d['client_secret']} (secret, for rig run --curve-secret); its public key is in "
        f"{d['clients_folder']} (for serve-sim --curve-clients)"]))
    return 0


def _task_options(args) -> dict:
    """The task and its options checked before the rig is contacted; a parse error names the option."""
    from magctl.rig.tasks import TaskError, available_tasks, resolve_options

    if args.task not in available_tasks():
        args.parser.error(f"argument --task: no task {args.task!r}; tasks: {', '.join(available_tasks())}")
    if args.task == "goto" and not args.target_um and not any(o.startswith("target") for o in args.option):
        args.parser.error("argument --target-um: goto needs a target (--target-um X Y)")
    options = {}
    if args.target_um:
        options["target_um"] = list(args.target_um)
    if args.goal_um:
        options["goal_um"] = list(args.goal_um)
    if args.kc is not None:
        options["kc"] = args.kc
    for item in args.option:
        key, sep, value = item.partition("=")
        if not sep or not key:
            args.parser.error(f"argument --option: {item!r}: write KEY=VALUE")
        try:
            options[key] = json.loads(value)
        except json.JSONDecodeError:
            options[key] = value
    try:
        resolve_options(args.task, options)
    except TaskError as err:
        args.parser.error(f"argument --option: {err}")
    return options


def cmd_run(args) -> int:
    from magctl.rig.interface import RigError
    from magctl.rig.runtime import Runtime, open_rig, set_realtime_priority

    options = _task_options(args)
    if args.view_controls and args.view is None:
        args.parser.error("argument --view-controls: needs --view")
    view = _start_view(args) if args.view is not None else None
    sched = set_realtime_priority(args.rt_priority)
    try:
        rig, desc = open_rig(args.rig, n_spheres=args.spheres, realtime=not args.fast, seed=args.seed,
                             plant=args.plant, reset=args.reset, takeover=args.takeover,
                             curve_server_key=args.curve_server_key, curve_secret=args.curve_secret,
                             scheduling=sched)
    except RigError as err:
        if view is not None:
            view[2].close()
        raise MagctlError(f"rig run: {err}") from None
    if view is not None:
        view[0].image_source = getattr(rig, "camera_view", None)   # a lab's camera frames, when the rig has them
    try:
        runtime = Runtime(rig, args.task, options, log_path=args.log, realtime=not args.fast,
                          max_ticks=args.max_ticks, duration=args.duration, seed=args.seed, quiet=args.quiet,
                          rig_description=desc, engine=args.engine,
                          # MB = 10^6 bytes; None: the run's rig.toml [log] max_mb
                          log_max_bytes=None if args.log_max_mb is None else int(round(args.log_max_mb * 1e6)),
                          monitor=None if view is None else view[0], controls=None if view is None else view[1])
        report = runtime.run()
    finally:
        rig.close()
        if view is not None:
            view[2].close()
    doc = report.stats()
    emit(args, doc, _summary)
    return 0 if doc["exit_status"] in ("done", "stopped") else 1


def _start_view(args):
    """The live page's feed, controls and server, started before the rig is opened (a taken address is a one-line
    error before any coil is live)."""
    from magctl.rig.monitor import RunControls
    from magctl.view.feed import LiveFeed
    from magctl.view.server import ViewServer

    feed = LiveFeed()
    controls = RunControls() if args.view_controls else None
    server = ViewServer.live(feed, args.view, controls)
    print(f"magctl rig run: live view at {server.url}" + ("" if controls else " (controls off: --view-controls)"),
          file=sys.stderr, flush=True)
    return feed, controls, server


def _summary(d: dict) -> str:
    lines = [f"exit: {d['exit_status']} — {d['reason']}", f"ticks: {d['ticks']}, overruns: {d['overruns']}"]
    if d.get("jitter_p99_ms") is not None:
        lines.append(f"tick jitter p50/p99/max: {d['jitter_p50_ms']:.3f}/{d['jitter_p99_ms']:.3f}/"
                     f"{d['jitter_max_ms']:.3f} ms; compute p50/p99: {d['compute_p50_ms']:.3f}/"
                     f"{d['compute_p99_ms']:.3f} ms")
    if d.get("robot_um") is not None:
        import numpy as np

        lines.append(f"robot: {np.round(d['robot_um'], 1).tolist()} µm; spheres: "
                     f"{np.round(d['spheres_um'], 1).tolist()} µm; status: {d.get('status')}")
    if d.get("log"):
        lines.append(f"log: {d['log']}")
    return "\n".join(lines)


def cmd_experiment(args) -> int:
    from magctl.identify.experiment import plan, run_experiment

    specs = plan()

    def progress(i, n, spec, report):
        if args.quiet or args.json:
            return
        if report is None:
            print(f"[{i}/{n}] {spec.name}: {spec.task} …", flush=True)
        else:
            print(f"[{i}/{n}] {spec.name}: {report.exit_status} ({report.final.get('status')}), "
                  f"{report.ticks} frames", flush=True)

    logs = run_experiment(args.rig, args.out, seed=args.seed, n_spheres=args.spheres, plant=args.plant,
                          progress=progress, specs=specs, engine=args.engine,
                          log_max_bytes=None if args.log_max_mb is None else int(round(args.log_max_mb * 1e6)))
    doc = {"logs": [str(p) for p in logs], "runs": [s.name for s in specs],
           "next": f"magctl identify {args.out}/*.jsonl --out IDENTIFIED"}
    emit(args, doc, lambda d: f"{len(d['logs'])} run logs in {args.out}\nnext: {d['next']}")
    return 0
