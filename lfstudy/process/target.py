"""The Snakemake ``process`` target's paths, checked before Snakemake removes anything.

Snakemake clears a job's declared outputs before the job starts, so lfstudy's own checks of
``--out`` would come too late for a ``directory()`` output: a recording kept under
``results/<name>/`` or a user's folder there would be gone. The rule therefore declares no
directory. Its output is a record beside the results, ``results/<name>.process.json`` (a copy
of the output's marker, written after a run succeeds), and ``lfstudy process --overwrite``
itself decides, under its lock, whether ``results/<name>/`` may be replaced (only an earlier
output of ``lfstudy process`` holding nothing but its own files). What Snakemake may remove
before the job, the record, is checked here at parse time.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from lfstudy.safe_output import output_marker

__all__ = ["ProcessTarget", "TargetError", "process_target"]


class TargetError(ValueError):
    """The process target's paths are unsafe (an input under the output, a foreign record)."""


@dataclass(frozen=True)
class ProcessTarget:
    """Where the ``process`` target writes.

    Attributes
    ----------
    out : str
        The output directory, ``results/<name>`` (relative to the working directory).
    record : str
        The rule's declared output: the marker of a finished run, copied beside the results.
    inputs : list of str
        The recording config and every file it names.
    """

    out: str
    record: str
    inputs: list[str]


def _record(path: Path) -> dict | None:
    """The process record at ``path`` (a marker of ``lfstudy process``), or None if it is something else."""
    try:
        marker = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return marker if isinstance(marker, dict) and marker.get("command") == "process" else None


def process_target(config_path: str | Path, name: str, inputs: list[str], workdir: str | Path = ".") -> ProcessTarget:
    """Check the process target's paths for recording ``name``; return them.

    Parameters
    ----------
    config_path : path
        The recording config (``--config process=...``).
    name : str
        Its ``name`` (already a plain name: the schema's pattern).
    inputs : list of str
        The files its ``recording`` section names (:func:`lfstudy.process.recording.recording_files`).
    workdir : path
        Snakemake's working directory (where ``results/`` lies).

    Raises
    ------
    TargetError
        An input lies under ``results/<name>/`` (Snakemake or an overwrite could remove it), or the
        record path holds a file lfstudy did not write. Nothing has been removed then.

    Notes
    -----
    A record whose output folder is gone or holds another run's marker is stale: it is removed
    here (it is lfstudy's own file), so Snakemake reruns the job.
    """
    wd = Path(workdir).resolve()
    out = f"results/{name}"
    record = f"results/{name}.process.json"
    out_abs = (wd / out).resolve()
    all_inputs = [str(config_path), *inputs]
    for inp in all_inputs:
        r = (wd / inp).resolve()
        if r == out_abs or out_abs in r.parents:
            raise TargetError(
                f"recording {str(config_path)!r}: {inp!r} lies inside {out}/, where the process target writes "
                f"its results (name: {name!r}); keep the recording outside results/, or give the recording another name"
            )
    rec = wd / record
    if rec.is_symlink() or rec.exists():
        written = None if rec.is_dir() else _record(rec)
        if written is None:
            raise TargetError(
                f"{record} exists and was not written by lfstudy process; Snakemake would remove it: move it away"
            )
        if written != output_marker(out_abs):
            rec.unlink()  # stale: the results were removed or replaced since; rerun
    return ProcessTarget(out=out, record=record, inputs=all_inputs)
