"""The client commands of `rayfarm`, on `service.client` (HTTP only).

    ID=$(rayfarm submit cornell-box --method path --spp 64 --depth 5)
    rayfarm watch $ID                  # a live progress bar until the job is final
    rayfarm fetch $ID -o cornell.exr   # --png: the preview; --wait: wait for the job first
    rayfarm jobs --status running      # a table of jobs, newest first
    rayfarm cancel $ID
    rayfarm logs $ID [UNIT]            # what units logged (default: those that failed or retried)
    rayfarm workers
    rayfarm upload scenes/room/scene.xml   # a scene with its folder; prints the scene's id
    rayfarm scenes [ID]                # the scenes; one with its import report

Every command takes `--server URL` (default: $RAYFARM_SERVER, else
http://127.0.0.1:8000) and `--token TOKEN` (default: $RAYFARM_TOKEN, the file
$RAYFARM_TOKEN_FILE, or the embedded service's ./rayfarm-data/admin.token). Results go to stdout (only the job id for `submit`),
messages to stderr. Exit codes: 0 done; 1 the job failed, was canceled or
deleted, or the service refused (no such job, wrong state); 2 an invalid
request (the field and its message are printed); 3 the service could not be
reached or failed.

Like the client, this module imports neither the server nor the renderer, so
the commands start quickly.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable

from .client import (DEFAULT_SERVER, FINAL_STATUSES, SCENE_SUFFIXES, ClientError, Conflict,
                     Invalid, NotFound, NotSupported, RayfarmClient, ServerError,
                     ServerUnavailable, mesh_files)

__all__ = ["add_client_commands", "EXIT_FAILED", "EXIT_INVALID", "EXIT_UNAVAILABLE"]

EXIT_FAILED = 1  # the job failed / was canceled, or the service refused the request
EXIT_INVALID = 2  # as argparse: the request (or its scene file) is invalid
EXIT_UNAVAILABLE = 3  # no service at the URL, or it failed


def _say(command: str, message: str) -> None:
    print(f"rayfarm {command}: {message}", file=sys.stderr, flush=True)


def _run(command: str, body: Callable[[argparse.Namespace, RayfarmClient], int]):
    """Wrap a command: open the client, turn every ClientError into a message and an exit code."""
    def run(args: argparse.Namespace) -> int:
        try:
            with RayfarmClient(args.server, timeout=args.timeout, token=args.token) as client:
                return body(args, client)
        except Invalid as exc:
            for field, message in exc.errors:
                _say(command, f"{field}: {message}")
            return EXIT_INVALID
        except (ServerUnavailable, ServerError) as exc:
            _say(command, str(exc))
            return EXIT_UNAVAILABLE
        except ClientError as exc:
            _say(command, str(exc))
            return EXIT_FAILED
        except KeyboardInterrupt:
            _say(command, "interrupted (jobs keep running on the service)")
            return 130
    return run


# -- formatting -----------------------------------------------------------------------------

def _duration(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    seconds = max(float(seconds), 0.0)
    if seconds < 60:
        return f"{seconds:.1f}s"
    minutes, secs = divmod(int(round(seconds)), 60)
    if minutes < 60:
        return f"{minutes}m{secs:02d}s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h{minutes:02d}m"


def _percent(e: float | None) -> str:
    """0.0183 -> 1.83 %; None (not known yet) -> ?"""
    return "?" if e is None else f"{100 * e:.3g} %"


def _count(n: float | None) -> str:
    """1234567 -> 1.23M (three significant digits), 512 -> 512."""
    if n is None:
        return "-"
    for factor, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(n) >= factor:
            return f"{n / factor:.3g}{suffix}"
    return f"{n:.3g}" if isinstance(n, float) else str(n)


def _table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(str(row[i])) for row in [header, *rows]) for i in range(len(header))]
    return "\n".join("  ".join(str(cell).ljust(w) for cell, w in zip(row, widths)).rstrip()
                     for row in [header, *rows])


# -- submit ---------------------------------------------------------------------------------

def _coerce_options(client: RayfarmClient, method: str, items: list[str]) -> dict[str, Any]:
    """`KEY=VALUE` pairs; values typed by the option tables of GET /methods
    (unknown methods and options stay strings: the service names the mistake)."""
    pairs = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise Invalid([("option", f"expects KEY=VALUE, got {item!r}")])
        pairs[key] = value
    if not pairs:
        return {}
    types = {}
    for entry in client.methods():
        if method == entry["name"] or method in entry.get("aliases", []):
            types = {o["name"]: o.get("type", "str") for o in entry.get("options", [])}
    out: dict[str, Any] = {}
    for key, value in pairs.items():
        kind = types.get(key, "str")
        try:
            if kind == "int":
                out[key] = int(value)
            elif kind == "float":
                out[key] = float(value)
            elif kind == "bool":
                lowered = value.lower()
                if lowered not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
                    raise ValueError(value)
                out[key] = lowered in ("true", "1", "yes", "on")
            else:
                out[key] = value
        except ValueError:
            raise Invalid([(f"options.{key}", f"expects a {kind}, got {value!r}")]) from None
    return out


def _print_report(command: str, record: dict) -> None:
    """An uploaded scene's import report, one entry a line, on stderr."""
    report = record.get("report") or []
    if not report:
        return
    _say(command, f"import report of {record.get('source') or record['name']}: "
                  f"{len(report)} element{'s' if len(report) != 1 else ''} not rendered as written")
    for entry in report:
        print("  " + _report_line(entry), file=sys.stderr, flush=True)


def _report_line(entry: dict) -> str:
    where = entry.get("file") or ""
    if entry.get("line") is not None:
        where += f":{entry['line']}"
    return ": ".join(part for part in (where, entry.get("element"), entry.get("action")) if part)


def _upload(command: str, client: RayfarmClient, path: Path, main: str | None = None) -> dict:
    record = client.upload_scene(path, main=main)
    _say(command, f"uploaded {path.name} as scene {record['id']}")
    _print_report(command, record)
    return record


def _scene_field(client: RayfarmClient, scene: str) -> str | dict:
    """A scene file, folder or archive is uploaded (with the files it names)
    and its id returned; a service without uploads gets a JSON file without
    files inline. Names and ids pass."""
    path = Path(scene)
    if not path.exists():
        if path.suffix.lower() in SCENE_SUFFIXES or os.sep in scene:
            raise Invalid([("scene", f"no such scene file: {scene}")])
        return scene  # a built-in scene's name or an uploaded scene's id
    try:
        record = _upload("submit", client, path)
    except NotSupported:
        if path.suffix.lower() != ".json" or not path.is_file():
            raise
        doc = json.loads(path.read_bytes())  # upload_scene has read and checked it
        meshes = mesh_files(doc, path.parent)
        if meshes:
            raise NotSupported(
                f"the service at {client.base_url} takes no scene uploads, and {path} "
                f"references mesh files ({', '.join(m.name for m in meshes)}), which only an "
                "upload carries; inline them as vertices/faces, or update the service") from None
        _say("submit", f"the service takes no scene uploads; sending {path.name} inline")
        return doc
    return record["id"]


def _upload_command(args: argparse.Namespace, client: RayfarmClient) -> int:
    path = Path(args.path)
    if not path.exists():
        raise Invalid([("scene", f"no such file or folder: {args.path}")])
    print(_upload("upload", client, path, args.main)["id"])
    return 0


def _scenes(args: argparse.Namespace, client: RayfarmClient) -> int:
    """The scenes as a table (REPORT: entries of its import report), or one
    scene with its report."""
    if args.id:
        scene = client.scene(args.id)
        if args.json:
            print(json.dumps(scene, indent=2))
            return 0
        for key in ("id", "kind", "name", "source", "description"):
            if scene.get(key):
                print(f"{key}: {scene[key]}")
        print(f"size: {scene['width']}x{scene['height']}, {scene['triangles']} triangles")
        report = scene.get("report") or []
        print(f"import report: {len(report)} element{'s' if len(report) != 1 else ''} not "
              "rendered as written" if report else "import report: every element as written")
        for entry in report:
            print("  " + _report_line(entry))
        return 0
    items = client.scenes()
    if args.json:
        print(json.dumps(items, indent=2))
        return 0
    print(_table(["ID", "KIND", "NAME", "SIZE", "TRIANGLES", "REPORT"], [[
        s["id"] if len(s["id"]) <= 24 else s["id"][:23] + "…", s["kind"], s["name"],
        f"{s['width']}x{s['height']}", str(s["triangles"]),
        str(len(s.get("report") or [])) if s["kind"] == "uploaded" else "-"] for s in items]))
    return 0


def _submit(args: argparse.Namespace, client: RayfarmClient) -> int:
    options = _coerce_options(client, args.method, args.option)
    job = client.submit(scene=_scene_field(client, args.scene), method=args.method,
                        spp=args.spp, depth=args.depth, tile_size=args.tile_size,
                        seed=args.seed, sampler=args.sampler, width=args.width,
                        height=args.height, options=options or None, priority=args.priority,
                        progressive=False if args.no_progressive else None,
                        denoise=True if args.denoise else None,
                        target=None if args.target is None else {
                            "rel_error": args.target, "max_seconds": args.max_seconds})
    print(job["id"], flush=True)  # stdout holds the id alone: ID=$(rayfarm submit ...)
    goal = (f"to {_percent(job['target']['rel_error'])} error, at most {job['spp']} spp"
            if job.get("target") else f"{job['spp']} spp")
    _say("submit", f"job {job['id']} {job['status']}: {job['scene']} {job['method']} "
                   f"{job['width']}x{job['height']} {goal} ({client.base_url})")
    if args.watch:
        return _follow(client, job["id"], quiet=args.quiet, command="submit")
    return 0


# -- watch ----------------------------------------------------------------------------------

class _ProgressBar:
    """A tqdm bar over a job's camera samples, with its status, rate and ETA
    as the service measures them (not tqdm's own estimates)."""

    def __init__(self, job_id: str, quiet: bool):
        self.job_id, self.quiet, self.bar = job_id, quiet, None

    def update(self, job: dict) -> None:
        if self.quiet:
            return
        progress, stats = job["progress"], job["stats"]
        total = max(int(progress["samples_total"]), 1)
        desc = f"{self.job_id} {job['status']:<8}"
        if job.get("target"):  # a target job's progress speaks in error
            text = (f"error {_percent(progress.get('rel_error'))} -> "
                    f"{_percent(progress.get('target_rel_error'))}, "
                    f"{len(job.get('passes') or [])} passes, "
                    f"{progress.get('units_skipped', 0)} units skipped, "
                    f"elapsed {_duration(progress['elapsed'])}, ETA {_duration(progress['eta'])}")
        else:
            text = (f"{_count(progress['samples_done'])}/{_count(progress['samples_total'])} "
                    f"samples, units {progress['units_done']}/{progress['units_total'] or '?'}, "
                    f"{_count(stats.get('samples_per_second'))} samples/s, "
                    f"elapsed {_duration(progress['elapsed'])}, ETA {_duration(progress['eta'])}")
        if self.bar is None:
            self.bar = _make_bar(total, min(int(progress["samples_done"]), total), desc, text)
            return
        self.bar.total, self.bar.stats = total, text
        self.bar.n = min(int(progress["samples_done"]), total)
        self.bar.set_description_str(desc, refresh=False)
        if job["status"] not in FINAL_STATUSES:  # the final state is drawn by close()
            self.bar.update(0)  # redraws once mininterval has passed

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _make_bar(total: int, done: int, desc: str, stats: str):
    from tqdm import tqdm

    class Bar(tqdm):
        """`{stats}` in the bar format: our own text, without tqdm's ', ' before a postfix."""

        def __init__(self, *args, stats: str, **kwargs):
            self.stats = stats  # before tqdm's constructor draws the first frame
            super().__init__(*args, **kwargs)

        @property
        def format_dict(self):
            return {**super().format_dict, "stats": self.stats}

    return Bar(total=total, initial=done, desc=desc, stats=stats, file=sys.stderr,
               dynamic_ncols=True, mininterval=0.2,
               bar_format="{desc} {percentage:3.0f}%|{bar}| {stats}")


def _follow(client: RayfarmClient, job_id: str, *, quiet: bool, command: str) -> int:
    bar = _ProgressBar(job_id, quiet)
    status = None
    try:
        for kind, data in client.events(job_id):
            if kind == "job":
                bar.update(data)
            elif kind == "end":
                status = data.get("status") if isinstance(data, dict) else None
    finally:
        bar.close()
    if status == "deleted":
        _say(command, f"job {job_id} was deleted")
        return EXIT_FAILED
    job = client.job(job_id)
    if job["status"] == "done":
        reached = (f", error {_percent(job['progress'].get('rel_error'))} (target "
                   f"{_percent(job['target']['rel_error'])}, stopped by {job['target_stop']})"
                   if job.get("target") else "")
        _say(command, f"job {job_id} done: {_count(job['samples'])} samples in "
                      f"{_duration(job['progress']['elapsed'])} "
                      f"({_count(job['stats']['samples_per_second'])} samples/s){reached}; "
                      f"rayfarm fetch {job_id} -o {job_id}.exr")
        return 0
    _say(command, f"job {job_id} {job['status']}: {job.get('error') or 'no error recorded'}")
    return EXIT_FAILED


def _watch(args: argparse.Namespace, client: RayfarmClient) -> int:
    return _follow(client, args.job_id, quiet=args.quiet, command="watch")


# -- fetch, jobs, cancel, workers -----------------------------------------------------------

def _fetch(args: argparse.Namespace, client: RayfarmClient) -> int:
    kind = "noise" if args.noise else "png" if args.png else "exr"
    default = {"exr": f"{args.job_id}.exr", "png": f"{args.job_id}.png",
               "noise": f"{args.job_id}-noise.png"}[kind]
    out = Path(args.output or default)
    job = client.wait(args.job_id) if args.wait else None
    if job is not None and job["status"] != "done" and kind == "exr" and not job.get("partial"):
        _say("fetch", f"job {args.job_id} {job['status']}: {job.get('error') or ''}".rstrip())
        return EXIT_FAILED
    download = {"exr": client.download_result, "png": client.download_preview,
                "noise": client.download_noise}[kind]
    try:
        download(args.job_id, out)
    except NotFound as exc:
        hint = "" if args.wait else " (rayfarm fetch --wait waits for it)"
        raise NotFound(f"{exc}{hint}", exc.status_code) from None
    job = job or client.job(args.job_id)
    if job.get("partial") and kind != "noise":
        _say("fetch", f"wrote {out} ({_count(out.stat().st_size)}B): partial, the "
                      f"{job['progress']['units_done']} of {job['progress']['units_total']} "
                      f"units job {args.job_id} finished before it was {job['status']}")
        return EXIT_FAILED if args.wait else 0
    _say("fetch", f"wrote {out} ({_count(out.stat().st_size)}B)")
    return 0


def _jobs(args: argparse.Namespace, client: RayfarmClient) -> int:
    filters = {k: getattr(args, k) for k in ("status", "method", "scene", "sampler", "owner")
               if getattr(args, k) is not None}
    jobs = client.jobs(limit=args.limit, **filters)
    if args.json:
        print(json.dumps(jobs, indent=2))
        return 0
    rows = [[j["id"], j["status"], j["scene"] if len(j["scene"]) <= 24 else j["scene"][:23] + "…",
             j["method"], j["sampler"], str(j["spp"]),
             f"{100 * j['progress']['fraction']:.0f}%", _duration(j["progress"]["elapsed"]),
             _duration(j["progress"]["eta"])] for j in jobs]
    print(_table(["ID", "STATUS", "SCENE", "METHOD", "SAMPLER", "SPP", "PROGRESS", "ELAPSED",
                  "ETA"], rows))
    if not jobs:
        _say("jobs", "no jobs" + (" with " + ", ".join(f"{k} {v}" for k, v in filters.items())
                                  if filters else ""))
    return 0


def _job_action(command: str):
    """cancel, pause, resume, retry, requeue, delete: the client's method of
    that name on each job id; prints "ID STATUS" (delete: "ID deleted"). A job
    that is not there or not in a state for it is said on stderr, exit 1."""
    def act(args: argparse.Namespace, client: RayfarmClient) -> int:
        code = 0
        for job_id in args.job_ids:
            try:
                job = getattr(client, command)(job_id)
            except (NotFound, Conflict) as exc:
                _say(command, str(exc))
                code = EXIT_FAILED
                continue
            print(f"{job_id} deleted" if job is None else f"{job['id']} {job['status']}")
        return code
    return act


def _priority(args: argparse.Namespace, client: RayfarmClient) -> int:
    job = client.set_priority(args.job_id, args.priority)
    print(f"{job['id']} priority {job['priority']}")
    return 0


def _listing(fetch: Callable[[RayfarmClient], list[dict]], header: list[str],
             row: Callable[[dict], list[str]]):
    """A registry command: the items as a table, or with --json as the API gave them."""
    def show(args: argparse.Namespace, client: RayfarmClient) -> int:
        items = fetch(client)
        print(json.dumps(items, indent=2) if args.json else _table(header, [row(i) for i in items]))
        return 0
    return show


_methods = _listing(RayfarmClient.methods,
                    ["METHOD", "ALIASES", "FAMILY", "AOVS", "NOISE TARGET", "OPTIONS"], lambda m: [
    m["name"], ",".join(m["aliases"]) or "-", m["family"], ",".join(m["aovs"]) or "-",
    "yes" if m.get("noise_target") else "no", ",".join(o["name"] for o in m["options"]) or "-"])


def _print_unit_log(entry: dict) -> None:
    print(f"== unit {entry['index']} ({entry['state']})"
          + (f": {entry['error']}" if entry.get("error") else ""))
    if not entry["attempts"]:
        print("   (no task has reported yet)")
    for attempt in entry["attempts"]:
        print(f"-- task {attempt['task']}, attempt {attempt['attempt']}: {attempt['outcome']}"
              + (f" on {attempt['worker']}" if attempt.get("worker") else ""))
        if attempt.get("dropped"):
            print(f"   ({attempt['dropped']} earlier lines dropped)")
        for line in attempt["lines"]:
            print(line)
        if attempt.get("traceback"):
            print(attempt["traceback"].rstrip("\n"))


def _logs(args: argparse.Namespace, client: RayfarmClient) -> int:
    if args.unit is not None:
        indices = [args.unit]
    else:  # the units worth reading: failed, or retried (more than one task)
        units = client.units(args.job_id)
        indices = [u["index"] for u in units
                   if args.all or u["state"] == "failed" or u["tasks"] > 1 or u.get("error")]
        if not indices:
            _say("logs", f"no unit of {args.job_id} failed or was retried "
                         f"({len(units)} units; --all prints every one, or name a UNIT)")
            return 0
    entries = [client.unit_log(args.job_id, i) for i in indices]
    if args.json:
        print(json.dumps(entries, indent=2))
        return 0
    for entry in entries:
        _print_unit_log(entry)
    return 0


def _workers(args: argparse.Namespace, client: RayfarmClient) -> int:
    if args.action is not None:
        if not args.name:
            _say("workers", f"workers {args.action}: name the worker (see `rayfarm workers`)")
            return EXIT_INVALID
        if args.action == "remove":
            client.remove_worker(args.name)
            print(f"{args.name} removed")
        else:
            worker = (client.disable_worker if args.action == "disable"
                      else client.enable_worker)(args.name)
            print(f"{worker['name']} {'disabled' if worker['disabled'] else 'enabled'} "
                  f"({worker['state']})")
        return 0
    workers = client.workers()
    if args.json:
        print(json.dumps(workers, indent=2))
        return 0
    rows = [[w["name"], w["kind"], w["state"] + (" (disabled)" if w.get("disabled") else ""),
             str(w["concurrency"]),
             ", ".join(f"{r['job_id']}/{r['index']}" for r in w["running"]) or "-",
             str(w["units_done"]), _count(w["samples_per_second"]),
             _duration(w["silent_seconds"]) + " ago"] for w in workers]
    print(_table(["NAME", "KIND", "STATE", "PROCS", "RUNNING", "UNITS", "SAMPLES/S",
                  "LAST SEEN"], rows))
    return 0


def _blocklist(args: argparse.Namespace, client: RayfarmClient) -> int:
    if args.clear:
        client.clear_blocklist(args.job_id, args.clear)
        print(f"{args.clear} cleared for job {args.job_id}")
        return 0
    rows = [[b["worker"], str(b["failures"]), "blocked" if b["blocked"] else "-",
             (b["last_error"] or "")[:60]] for b in client.blocklist(args.job_id)]
    print(_table(["WORKER", "FAILURES", "STATE", "LAST ERROR"], rows))
    return 0


def _experiment_table(experiment: dict) -> str:
    rows = []
    for config in experiment["report"]:
        for i, level in enumerate(config["levels"]):
            rows.append([config["label"] if i == 0 else "", str(level["spp"]),
                         f"{level['biased_blocks']}/{level['blocks']}",
                         f"{level['bias_p']:.2g}", "yes" if level["unbiased"] else "no",
                         f"{100 * level['relative_bias']:+.2f}%", f"{level['variance']:.3g}",
                         f"{level['mse']:.3g}", f"{1000 * level['seconds']:.3g}ms"
                         if level["seconds"] < 1 else _duration(level["seconds"]),
                         f"{level['efficiency']:.3g}" if level["efficiency"] else "-",
                         f"{config['slope']:.2f}" if i == 0 and config["slope"] is not None else "",
                         ("yes" if config["unbiased"] else "no") if i == 0 else "",
                         ("?" if config["consistent"] is None else
                          "yes" if config["consistent"] else "no") if i == 0 else ""])
    return _table(["CONFIG", "SPP", "SIG. BLOCKS", "BIAS P", "UNBIASED", "MEAN BIAS", "VARIANCE", "MSE", "TIME",
                   "EFFICIENCY", "SLOPE", "UNBIASED?", "CONSISTENT?"], rows)


def _show_experiment(args: argparse.Namespace, client: RayfarmClient, experiment: dict) -> int:
    if args.json:
        print(json.dumps(experiment, indent=2))
    elif experiment["status"] != "done":
        print(f"{experiment['id']} {experiment['status']} "
              f"({experiment['jobs_done']}/{experiment['jobs_total']} jobs)"
              + (f": {experiment['error']}" if experiment["error"] else ""))
    elif args.csv:
        sys.stdout.write(client.experiment_csv(experiment["id"]))
    else:
        print(_experiment_table(experiment))
    return 0 if experiment["status"] in ("done", "running") else EXIT_FAILED


def _wait_experiment(client: RayfarmClient, experiment_id: str, quiet: bool) -> dict:
    bar = None
    while True:
        experiment = client.experiment(experiment_id)
        if not quiet:
            if bar is None:
                bar = _make_bar(experiment["jobs_total"], 0, f"experiment {experiment_id}", "")
            bar.n = experiment["jobs_done"]
            bar.refresh()
        if experiment["status"] != "running":
            if bar is not None:
                bar.close()
            return experiment
        time.sleep(1.0)


def _experiment(args: argparse.Namespace, client: RayfarmClient) -> int:
    if args.show:
        experiment = client.experiment(args.show)
    elif args.list:
        rows = [[e["id"], e["status"], e["request"]["scene"], ",".join(e["request"]["labels"]),
                 ",".join(map(str, e["request"]["spp"])), str(e["request"]["repeats"]),
                 f"{e['jobs_done']}/{e['jobs_total']}"] for e in client.experiments()]
        print(_table(["ID", "STATUS", "SCENE", "CONFIGS", "SPP", "REPEATS", "JOBS"], rows))
        return 0
    else:
        if not args.scene or not args.methods:
            _say("experiment", "give a scene and --methods (or --show ID, or --list)")
            return EXIT_INVALID
        configs = [{"method": m, "sampler": args.sampler} for m in args.methods]
        experiment = client.create_experiment(
            scene=args.scene, configs=configs, spp=args.spp, repeats=args.repeats,
            depth=args.depth, width=args.width, height=args.height or args.width,
            block=args.block, seed=args.seed,
            reference={"job": args.reference} if args.reference else None)
        _say("experiment", f"{experiment['id']}: {experiment['jobs_total']} jobs submitted")
        if not args.wait:
            print(experiment["id"])
            return 0
    if args.wait and experiment["status"] == "running":
        experiment = _wait_experiment(client, experiment["id"], args.quiet)
    return _show_experiment(args, client, experiment)


# -- the parsers ------------------------------------------------------------------------------

def _server_options() -> argparse.ArgumentParser:
    parent = argparse.ArgumentParser(add_help=False)
    default = os.environ.get("RAYFARM_SERVER") or DEFAULT_SERVER
    parent.add_argument("--server", default=default, metavar="URL",
                        help=f"the rayfarm service (default: $RAYFARM_SERVER or {DEFAULT_SERVER}; "
                             f"now {default})")
    parent.add_argument("--token", default=None, metavar="TOKEN",
                        help="API token (default: $RAYFARM_TOKEN, the file $RAYFARM_TOKEN_FILE, "
                             "or ./rayfarm-data/admin.token)")
    parent.add_argument("--timeout", type=float, default=30.0, metavar="SECONDS",
                        help="how long to wait for an answer (default: 30)")
    return parent


def add_client_commands(sub: argparse._SubParsersAction) -> None:
    """Add the client commands (submit, watch, fetch, jobs, the job actions, priority,
    scenes, methods, logs, workers, experiment, blocklist) to `rayfarm`'s subcommands."""
    server = [_server_options()]

    submit = sub.add_parser("submit", parents=server, help="submit a render job; prints its id",
                            description="Submit a render job to the service; prints the job id "
                                        "(alone) on stdout.")
    submit.add_argument("scene", help="a built-in scene name, an uploaded scene's id, or a path "
                                      "to a scene file (JSON, Mitsuba XML, glTF), folder or "
                                      "archive (uploaded with its files, as `rayfarm upload`)")
    submit.add_argument("--method", default="path", help="rendering method (default: path; "
                                                         "the service lists them at /methods)")
    submit.add_argument("--spp", type=int, default=16, help="samples per pixel (default: 16)")
    submit.add_argument("--depth", type=int,
                        help="surface bounces: 0 = emitters only, 1 = direct light (default: the "
                             "scene's, from an imported file's integrator block, else 5)")
    submit.add_argument("--sampler", help="pixel sampler (default: the service's, sobol)")
    submit.add_argument("--width", type=int, help="image width (default: the scene camera's)")
    submit.add_argument("--height", type=int, help="image height (default: the scene camera's)")
    submit.add_argument("--tile-size", type=int, help="side of a work unit's tile in pixels")
    submit.add_argument("--seed", type=int, help="random seed (same seed, same pixels)")
    submit.add_argument("--priority", type=int, help="-100..100, higher runs first (default: 0)")
    submit.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="a method option, e.g. --option heuristic=balance (repeatable)")
    submit.add_argument("--no-progressive", action="store_true",
                        help="render all samples of a tile in one unit (no improving preview)")
    submit.add_argument("--denoise", action="store_true",
                        help="when done, also denoise the merged frame (denoised.R/G/B in the "
                             "EXR, beside the raw image)")
    submit.add_argument("--target", type=float, metavar="REL_ERROR",
                        help="render to a noise target instead of a fixed spp, e.g. 0.01: "
                             "passes are added tile by tile until the 95th percentile of the "
                             "pixels' relative standard error is at most that; --spp is then "
                             "the most samples per pixel")
    submit.add_argument("--max-seconds", type=float,
                        help="with --target: stop adding passes after this long")
    submit.add_argument("--watch", action="store_true",
                        help="then follow the job like `rayfarm watch`")
    submit.add_argument("--quiet", action="store_true", help="with --watch: no progress bar")
    submit.set_defaults(run=_run("submit", _submit))

    watch = sub.add_parser("watch", parents=server, help="follow a job with a progress bar",
                           description="Follow a job's progress live until it is final; exit "
                                       "0 when done, 1 when it failed or was canceled.")
    watch.add_argument("job_id", metavar="ID")
    watch.add_argument("--quiet", action="store_true", help="no progress bar; only the outcome")
    watch.set_defaults(run=_run("watch", _watch))

    fetch = sub.add_parser("fetch", parents=server, help="download a job's EXR (or preview)",
                           description="Download a done job's EXR, or its preview or noise PNG.")
    fetch.add_argument("job_id", metavar="ID")
    fetch.add_argument("-o", "--output", metavar="PATH",
                       help="where to write it (default: ID.exr, ID.png or ID-noise.png)")
    kind = fetch.add_mutually_exclusive_group()
    kind.add_argument("--png", action="store_true", help="the tonemapped preview PNG instead")
    kind.add_argument("--noise", action="store_true", help="the noise heatmap PNG instead")
    fetch.add_argument("--wait", action="store_true", help="wait for the job to be final first")
    fetch.set_defaults(run=_run("fetch", _fetch))

    jobs = sub.add_parser("jobs", parents=server, help="list jobs, newest first")
    jobs.add_argument("--status", help="only jobs with this status (queued, running, paused, "
                                       "done, failed, canceled)")
    jobs.add_argument("--method", help="only jobs of this method (an alias counts)")
    jobs.add_argument("--scene", help="only jobs of this scene (as the jobs list names it)")
    jobs.add_argument("--sampler", help="only jobs with this pixel sampler")
    jobs.add_argument("--owner", help="only jobs of this user")
    jobs.add_argument("--limit", type=int, default=20, help="at most this many (default: 20)")
    jobs.add_argument("--json", action="store_true", help="the jobs as JSON instead of a table")
    jobs.set_defaults(run=_run("jobs", _jobs))

    for command, text in (("cancel", "cancel jobs"),
                          ("pause", "pause jobs (their units in flight finish)"),
                          ("resume", "resume paused jobs"),
                          ("retry", "run a job's failed units again"),
                          ("requeue", "start jobs again from nothing"),
                          ("delete", "delete jobs, their units and images")):
        action = sub.add_parser(command, parents=server, help=text)
        action.add_argument("job_ids", nargs="+", metavar="ID")
        action.set_defaults(run=_run(command, _job_action(command)))

    priority = sub.add_parser("priority", parents=server, help="change a job's priority")
    priority.add_argument("job_id", metavar="ID")
    priority.add_argument("priority", type=int, help="-100..100, higher runs first")
    priority.set_defaults(run=_run("priority", _priority))

    for command, body, text in (("scenes", _scenes, "list the scenes jobs may name, or show "
                                                    "one with its import report"),
                                ("methods", _methods, "list the rendering methods")):
        listing = sub.add_parser(command, parents=server, help=text)
        if command == "scenes":
            listing.add_argument("id", nargs="?", metavar="ID",
                                 help="show this scene (and its import report)")
        listing.add_argument("--json", action="store_true", help="JSON instead of a table")
        listing.set_defaults(run=_run(command, body))

    upload = sub.add_parser("upload", parents=server, help="upload a scene; prints its id",
                            description="Upload a scene: a JSON file with the files it names, "
                                        "a Mitsuba .xml or glTF file with its folder, a folder, "
                                        "or an archive (.zip, .tar, .tar.gz). Prints the scene's "
                                        "id (alone) on stdout and its import report (what is "
                                        "not rendered as written) on stderr.")
    upload.add_argument("path", metavar="PATH", help="a scene file, a folder or an archive")
    upload.add_argument("--main", metavar="FILE",
                        help="the scene file's path inside a folder or archive that holds "
                             "several at its top level")
    upload.set_defaults(run=_run("upload", _upload_command))

    logs = sub.add_parser("logs", parents=server, help="print what a job's units logged",
                          description="Print the log lines and tracebacks a job's units left, "
                                      "per task: of UNIT, or of the units that failed or were "
                                      "retried.")
    logs.add_argument("job_id", metavar="JOB")
    logs.add_argument("unit", metavar="UNIT", type=int, nargs="?", help="a unit's index")
    logs.add_argument("--all", action="store_true", help="every unit (without UNIT)")
    logs.add_argument("--json", action="store_true", help="as JSON")
    logs.set_defaults(run=_run("logs", _logs))

    workers = sub.add_parser("workers", parents=server, help="list, drain or remove render workers",
                             description="List the render workers; admins disable (drain: "
                                         "running units finish, no new ones), enable, or remove "
                                         "a lost or offline one.")
    workers.add_argument("action", nargs="?", choices=["disable", "enable", "remove"])
    workers.add_argument("name", nargs="?", metavar="NAME", help="the worker (as listed)")
    workers.add_argument("--json", action="store_true", help="as JSON instead of a table")
    workers.set_defaults(run=_run("workers", _workers))

    lab = sub.add_parser("experiment", parents=server,
                         help="run an estimator-lab experiment, or show one (table, CSV, JSON)",
                         description="The estimator lab: every method at every spp level, "
                                     "--repeats times, measured against a reference (bias and "
                                     "its test, variance, MSE, time, efficiency, slope, "
                                     "unbiased? consistent?). Without --wait, prints the "
                                     "experiment's id.")
    lab.add_argument("scene", nargs="?", help="a built-in scene name or an uploaded scene's id")
    lab.add_argument("--methods", nargs="+", metavar="METHOD", help="the methods to compare")
    lab.add_argument("--sampler", default="random", help="their pixel sampler (default: random)")
    lab.add_argument("--spp", nargs="+", type=int, default=[1, 4, 16, 64],
                     help="spp levels (default: 1 4 16 64)")
    lab.add_argument("--repeats", type=int, default=4, help="renders per level (default: 4)")
    lab.add_argument("--depth", type=int, default=5)
    lab.add_argument("--width", type=int, default=32, help="image width (default: 32)")
    lab.add_argument("--height", type=int, default=None, help="(default: the width)")
    lab.add_argument("--block", type=int, default=8, help="bias test block side (default: 8)")
    lab.add_argument("--seed", type=int, default=0)
    lab.add_argument("--reference", metavar="JOB", help="a done job to measure against "
                                                        "(default: one is rendered)")
    lab.add_argument("--show", metavar="ID", help="show an experiment instead")
    lab.add_argument("--list", action="store_true", help="list the experiments")
    lab.add_argument("--wait", action="store_true", help="wait for it, then print its report")
    lab.add_argument("--quiet", action="store_true", help="no progress bar while waiting")
    form = lab.add_mutually_exclusive_group()
    form.add_argument("--csv", action="store_true", help="the report as CSV")
    form.add_argument("--json", action="store_true", help="the experiment as JSON")
    lab.set_defaults(run=_run("experiment", _experiment))

    blocked = sub.add_parser("blocklist", parents=server,
                             help="the workers blocklisted for a job; --clear one",
                             description="The workers that failed units of a job (blocklisted "
                                         "for it after worker_failures_per_job); --clear takes "
                                         "one off (its owner or an admin).")
    blocked.add_argument("job_id", metavar="ID")
    blocked.add_argument("--clear", metavar="WORKER", help="take this worker off the blocklist")
    blocked.set_defaults(run=_run("blocklist", _blocklist))
