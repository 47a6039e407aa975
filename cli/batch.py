"""``proxycodec batch``: one command over many scenes, on Ray when it is installed (a thin layer over
``proxycodec.batch``)."""

from __future__ import annotations

import click

from .common import user_errors


def split_args(command: click.Command, args: list[str]) -> tuple[list[str], list[str]]:
    """(inputs, the command's options) from what follows ``batch COMMAND``: an option of ``command`` takes its
    value with it (``--opt VALUE`` or ``--opt=VALUE``; flags none), anything else is an input."""
    from ..errors import ProxycodecError

    takes_value = {}
    for p in command.params:
        if isinstance(p, click.Option):
            for name in p.opts + p.secondary_opts:
                takes_value[name] = not (p.is_flag or p.count) and name not in p.secondary_opts
    inputs, options = [], []
    i = 0
    while i < len(args):
        a = args[i]
        if a.startswith("-") and a != "-":
            name = a.split("=", 1)[0]
            if name not in takes_value:
                raise ProxycodecError(f"`proxycodec {command.name}` has no option {name}")
            options.append(a)
            if takes_value[name] and "=" not in a:
                if i + 1 >= len(args):
                    raise ProxycodecError(f"{name} needs a value")
                options.append(args[i + 1])
                i += 1
        else:
            inputs.append(a)
        i += 1
    return inputs, options


@click.command(context_settings={"ignore_unknown_options": True})
@click.argument("command", type=click.Choice(["encode", "convert", "fit", "eval"]))
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for the outputs (NAME.pxc / NAME.ply / NAME_eval), logs/ and batch.json + batch.md.")
@click.option("--dataset", type=click.Path(file_okay=False), default=None,
              help="batch eval: the dataset every scene is evaluated on.")
@click.option("--ray/--no-ray", "use_ray", default=None,
              help="Run on Ray [default: when it is installed] or one task after another here.")
@click.option("--ray-address", default=None,
              help="An existing Ray cluster (auto, ray://host:port) [default: a local Ray started here with this "
                   "machine's cores].")
@click.option("--cpus-per-task", type=click.FloatRange(min=0.01), default=None,
              help="CPUs a task reserves on Ray; also its threads [default: 1 on Ray; here: the command's own].")
@click.option("--gpus-per-task", type=click.FloatRange(min=0.0), default=0.0, show_default=True,
              help="GPUs a task reserves on Ray.")
@click.option("--retries", type=click.IntRange(min=0), default=0, show_default=True,
              help="Retries of a task that crashed (a user error, exit 2, is not retried).")
@user_errors
def batch(command, args, out_dir, dataset, use_ray, ray_address, cpus_per_task, gpus_per_task, retries) -> None:
    """Run COMMAND (encode, convert, fit or eval) on every input, one task per scene:
    `proxycodec batch encode a.ply b.ply --out DIR --no-distill`.

    \b
    Reads the inputs as COMMAND does (eval: the scenes, with --dataset); COMMAND's own options pass through.
    Writes DIR/NAME.pxc (encode), DIR/NAME.ply (convert, fit) or DIR/NAME_eval/ (eval), each task's log in
    DIR/logs/NAME.log, and a summary (bytes, PSNR where the command measures one, seconds, peak RSS) in
    DIR/batch.json and DIR/batch.md. A failing scene gets its one-line error and never stops the others; a
    re-run skips what finished with the same input bytes and options. Each task is COMMAND run alone in a
    child process: its output is byte-identical to running it by hand with the same options and threads.
    Ray is optional (pip install -e ".[ray]"); without it the tasks run one after another here.
    """
    import sys

    from ..batch import plan, run_batch, summary_markdown, write_summary
    from ..errors import ProxycodecError

    root = click.get_current_context().find_root()
    inputs, options = split_args(root.command.get_command(root, command), list(args))
    if not inputs:
        raise ProxycodecError(f"batch {command}: no inputs given")
    threads = None if cpus_per_task is None else max(1, int(cpus_per_task))
    tasks = plan(command, inputs, out_dir, options, dataset=dataset, threads=threads)
    records, how = run_batch(tasks, use_ray=use_ray, ray_address=ray_address, cpus_per_task=cpus_per_task or 1.0,
                             gpus_per_task=gpus_per_task, retries=retries,
                             say=lambda s: click.echo(s, err=True))
    paths = write_summary(out_dir, records, how)
    click.echo(summary_markdown(records, how))
    click.echo(f"wrote {paths['json']} and {paths['markdown']}")
    if any(r["status"] == "error" for r in records):
        sys.exit(1)
