"""``flexdof workflow run|status``: batch, distributed and scheduled runs of a workflow file.

Exit codes of ``run``: 0 every stack is done; 1 some stack failed (listed);
2 the workflow or a flag is invalid (nothing was processed); 75 another run of
the workflow holds the lock (EX_TEMPFAIL: try again later).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import logging
import sys
import time

from pipeline.commands import _flags, print_json

log = logging.getLogger(__name__)

EXIT_FAILED = 1
EXIT_LOCKED = 75


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "workflow",
        help="batch, distributed and scheduled runs of a workflow file",
        description="Process every stack a workflow file names (workflows/*.toml), only those "
        "new or changed since the last run, recording each in a ledger in the output folder.",
    )
    sub = parser.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    run = sub.add_parser("run", help="process new or changed stacks (once, or --every)")
    run.add_argument("file", help="workflow file (TOML)")
    run.add_argument(
        "--every",
        metavar="INTERVAL",
        help="repeat every INTERVAL (e.g. 15m, 1h) (default: the "
        "workflow's [schedule] every with --scheduled, else run once)",
    )
    run.add_argument(
        "--scheduled", action="store_true", help="loop on the workflow's [schedule] every"
    )
    run.add_argument("--runs", type=int, help="with --every: stop after this many runs")
    run.add_argument(
        "--concurrency",
        type=int,
        help="stacks in flight, bounds memory (default: the workflow file's)",
    )
    run.add_argument(
        "--retry-failed",
        action="store_true",
        help="also retry stacks whose unchanged inputs failed before",
    )
    run.add_argument(
        "--dry-run",
        action="store_true",
        help="list what would be processed and why; process nothing",
    )
    processing = run.add_argument_group(
        "processing (default: the workflow file's options, else those of flexdof stack)"
    )
    _flags.add_processing(processing, defaults=False)
    _flags.add_json(run)
    run.set_defaults(func=run_command)
    status = sub.add_parser("status", help="print the workflow's ledger")
    status.add_argument("file", help="workflow file (TOML)")
    _flags.add_json(status)
    status.set_defaults(func=status_command)


def _overrides(args: argparse.Namespace) -> dict:
    given = {
        "lens": args.lens,
        "method": args.method,
        "align": args.align,
        "align_model": args.align_model,
        "blur_span_px": args.blur_span_px,
        "white": args.white,
        "tile_px": args.tile_px,
        "frame_guard": args.frame_guard,
        "frame_range": args.frame_range,
        "match_exposure": args.match_exposure,
        "crop": args.crop,
        "concurrency": args.concurrency,
        "threads_per_stack": args.threads,
        "scheduler": args.scheduler,
    }
    if args.retry_failed:
        given["retry_failed"] = True
    return {key: value for key, value in given.items() if value is not None}


class _Reporter:
    """Whole-batch and per-stack progress: rich bars on a terminal, else log lines."""

    def __init__(self, quiet: bool, dry_run: bool = False) -> None:
        self.quiet, self.dry_run = quiet, dry_run
        self.bars = None
        self.total = 0
        self.count = 0

    @contextlib.contextmanager
    def session(self):
        if self.quiet or not sys.stderr.isatty():
            yield self
            return
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

        self.bars = Progress(
            TextColumn("{task.description:<40}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[stage]}"),
        )
        self.tasks: dict[str, int] = {}
        with self.bars:
            self.batch = self.bars.add_task("batch", total=0, stage="")
            yield self
        self.bars = None

    def plan(self, todo, up_to_date: int) -> None:
        self.total = len(todo)
        if self.bars is not None:
            self.bars.update(self.batch, total=len(todo))
        if not self.quiet or self.dry_run:
            out = sys.stdout if self.dry_run else sys.stderr  # a dry run's plan is its result
            verb = "would process" if self.dry_run else "to process"
            print(f"{len(todo)} stack(s) {verb}, {up_to_date} up to date or not retried", file=out)
            for stack, reason in todo:
                print(f"  {stack.id}: {reason}", file=out)

    def progress(self, key: str, stage: str, done: int, total: int) -> None:
        if self.bars is None:
            return
        if key not in self.tasks:
            self.tasks[key] = self.bars.add_task(key[-40:], total=None, stage="")
        self.bars.update(self.tasks[key], completed=done, total=total or None, stage=stage)

    def result(self, result: dict) -> None:
        self.count += 1
        if self.bars is not None:
            self.bars.update(self.batch, advance=1)
            if result["key"] in self.tasks:
                self.bars.remove_task(self.tasks.pop(result["key"]))
        if self.quiet:
            return
        head = f"[{self.count}/{self.total}]"
        if result["status"] == "done":
            print(
                f"{head} done   {result['key']} -> {result['output']} ({result['seconds']:.1f} s)",
                file=sys.stderr,
            )
        else:
            print(f"{head} FAILED {result['key']}: {result['error']}", file=sys.stderr)


def _print_summary(summary, quiet: bool) -> None:
    if not quiet:
        print(
            f"run {summary.run_id}: {len(summary.done)} done, {len(summary.failed)} failed, "
            f"{len(summary.skipped)} up to date, in {summary.seconds:.1f} s"
        )
    for key, error in summary.failed:
        print(f"failed: {key}: {error}", file=sys.stderr)


def run_command(args: argparse.Namespace) -> int:
    from pipeline.workflow.ledger import LockedError
    from pipeline.workflow.run import run_every, run_workflow
    from pipeline.workflow.schema import load_workflow, parse_interval

    workflow = load_workflow(args.file, overrides=_overrides(args))
    every = args.every
    if every is None and args.scheduled:
        if workflow.every_s is None:
            print(
                f"flexdof workflow: error: {workflow.path} has no [schedule] every; give --every",
                file=sys.stderr,
            )
            return 2
        interval = workflow.every_s
    else:
        interval = None if every is None else parse_interval(every, where="--every")
    if args.runs is not None and (args.runs < 1 or interval is None):
        print(
            "flexdof workflow: error: --runs N (N >= 1) goes with --every or --scheduled",
            file=sys.stderr,
        )
        return 2
    status = [0]

    def once() -> bool:
        current = load_workflow(args.file, overrides=_overrides(args))
        reporter = _Reporter(args.quiet or args.json, dry_run=args.dry_run and not args.json)
        with reporter.session():
            summary = run_workflow(
                current,
                dry_run=args.dry_run,
                on_plan=reporter.plan,
                on_result=reporter.result,
                on_progress=reporter.progress,
                empty_ok=True if interval is not None else None,
            )
        if args.json:
            print_json(
                {
                    "run": summary.run_id,
                    "planned": summary.planned,
                    "dry_run": args.dry_run,
                    "done": summary.done,
                    "failed": [{"stack": k, "error": e} for k, e in summary.failed],
                    "up_to_date": summary.skipped,
                    "seconds": summary.seconds,
                }
            )
        elif not args.dry_run:
            _print_summary(summary, args.quiet)
        status[0] = 0 if summary.ok else EXIT_FAILED
        return summary.ok

    try:
        if interval is None:
            once()
            return status[0]

        def report(err: Exception) -> None:
            status[0] = EXIT_LOCKED if isinstance(err, LockedError) else 2
            print(f"flexdof workflow: {datetime.datetime.now():%H:%M:%S}: {err}", file=sys.stderr)

        if not args.quiet:
            print(
                f"running {workflow.path.name} every {interval:g} s (Ctrl-C to stop)",
                file=sys.stderr,
            )
        run_every(interval, once, runs=args.runs, on_error=report)
        return status[0]
    except LockedError as err:
        print(f"flexdof workflow: refused: {err}", file=sys.stderr)
        return EXIT_LOCKED


def _when(stamp: float | None) -> str:
    return "-" if stamp is None else time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(stamp))


def status_command(args: argparse.Namespace) -> int:
    from pipeline.workflow.ledger import Ledger
    from pipeline.workflow.schema import load_workflow

    workflow = load_workflow(args.file)
    if not workflow.ledger_path.is_file():
        print(f"{workflow.name}: no runs yet (no ledger at {workflow.ledger_path})")
        return 0
    with Ledger(workflow.ledger_path) as ledger:
        records, runs = ledger.records(), ledger.runs()
    if args.json:
        print_json(
            {
                "workflow": str(workflow.path),
                "ledger": str(workflow.ledger_path),
                "runs": runs,
                "stacks": [r.__dict__ for r in records],
            }
        )
        return 0
    if runs:
        last = runs[-1]
        print(
            f"{workflow.name}: {len(runs)} run(s); last #{last['id']} {last['status']} "
            f"started {_when(last['started'])}: {last['done']} done, {last['failed']} "
            f"failed, {last['skipped']} up to date"
        )
    width = max([len(r.stack) for r in records] + [5])
    print(f"{'stack':<{width}}  {'status':<11}  {'seconds':>7}  {'finished':<19}  output / error")
    for r in records:
        seconds = "-" if r.seconds is None else f"{r.seconds:.1f}"
        tail = r.output if r.status == "done" else (r.error or "")
        print(f"{r.stack:<{width}}  {r.status:<11}  {seconds:>7}  {_when(r.finished):<19}  {tail}")
    failed = sum(r.status == "failed" for r in records)
    return EXIT_FAILED if failed else 0
