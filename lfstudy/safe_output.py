"""Outputs written so that nothing is lost: atomic stores, and command outputs that never replace data
lfstudy did not write.

Every output is written into a temporary sibling and moved into place when complete, so an
interrupted job leaves the earlier version (or nothing), never a half-written store. The
temporaries, the lock and the swap's parking place are named ``.NAME.lfstudy-<kind>-HOST-PID-RANDOM``:
a name no user file takes by chance, and the writer it belongs to is known, so only a dead
writer's leftovers of this host are cleared, and an earlier output parked by a writer killed in the
middle of its swap is moved back.

A command's output directory (:func:`output_dir`) carries a marker, :data:`MARKER`, that names the
command and lists every file it wrote. ``--overwrite`` replaces such an output only while it holds
nothing else: a file added to it later (notes, a copied recording) makes the run refuse, naming the
file, before any processing and again at the swap.
"""

from __future__ import annotations

import glob
import json
import os
import re
import shutil
import socket
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager, suppress
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

__all__ = ["MARKER", "OutputError", "atomic_path", "check_output", "clear_stale", "output_dir", "output_marker"]

#: The file every command's output carries: which command wrote it, when, from what, and its files.
MARKER = ".lfstudy-output.json"

#: The kinds of sibling a writer makes: its temporary, the earlier version parked during the swap,
#: and the probe that checks, before any processing, that an existing output can be moved.
_KINDS = ("tmp", "old", "probe")
_SIGNATURE = b"lfstudy output lock\n"


class OutputError(ValueError):
    """An output path a command will not write: it holds data lfstudy did not write (or an
    earlier output, without ``overwrite``), inputs of the run, or its folder cannot be written."""


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9_.]", "_", socket.gethostname()) or "host"


def _sibling(path: Path, kind: str) -> Path:
    """``.NAME.lfstudy-KIND-HOST-PID-RANDOM`` beside ``path``: named by its writer."""
    return path.with_name(f".{path.name}.lfstudy-{kind}-{_host()}-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):  # another user's process (alive); a number no PID can be
        return True
    return True


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    elif p.exists() or p.is_symlink():
        p.unlink()


def clear_stale(path: str | Path) -> list[Path]:
    """Tidy the siblings of ``path`` left by killed writers of this host (SIGKILL skips their cleanup).

    A dead writer's temporary is removed. An earlier output it had parked for its swap
    (``old``, ``probe``) is moved back to ``path`` when nothing is there (the writer died
    mid-swap: the earlier output is the only complete one), and removed when the new output
    is in place. A live writer's siblings, another host's (a cluster's shared file system),
    and anything not named as ours are left alone.

    Returns
    -------
    list of Path
        The siblings removed or moved back.
    """
    path = Path(path)
    host = _host()
    done = []
    pattern = re.compile(rf"\.{re.escape(path.name)}\.lfstudy-({'|'.join(_KINDS)})-(.+)-(\d+)-[0-9a-f]{{8}}")
    for stale in sorted(path.parent.glob(f".{glob.escape(path.name)}.lfstudy-*")):
        m = pattern.fullmatch(stale.name)
        if m is None or m.group(2) != host or _pid_alive(int(m.group(3))):
            continue
        if m.group(1) == "tmp":
            _remove(stale)
        elif not (path.exists() or path.is_symlink()):
            os.replace(stale, path)  # the writer died between parking the earlier output and the swap
        elif m.group(1) == "old":
            _remove(stale)
        else:
            continue  # a probe of a directory that was replaced since: not provably ours to delete
        done.append(stale)
    return done


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling path; on success replace ``path`` with it.

    On any exception the temporary output is removed and ``path`` is left as
    it was (absent, or the previous complete version). Whatever is at ``path``
    is replaced: this is for outputs the caller owns (a workflow's stores);
    a command's ``--out`` goes through :func:`output_dir`, which refuses to
    replace what lfstudy did not write.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clear_stale(path)
    tmp = _sibling(path, "tmp")
    try:
        yield tmp
        _swap(tmp, path)
    finally:
        if tmp.exists():
            _remove(tmp)


def _swap(tmp: Path, path: Path, check_old: Any = None) -> None:
    """Move ``tmp`` to ``path``; an existing ``path`` is parked first and removed after.

    ``check_old(parked)`` may refuse what was there (it raises): then it is moved back and
    ``path`` is as it was.
    """
    if not (path.exists() or path.is_symlink()):
        os.replace(tmp, path)
        return
    old = _sibling(path, "old")
    os.replace(path, old)
    try:
        if check_old is not None:
            check_old(old)
        os.replace(tmp, path)
    except BaseException:
        if not (path.exists() or path.is_symlink()):
            os.replace(old, path)
        raise
    _remove(old)


def output_marker(path: str | Path) -> dict[str, Any] | None:
    """The marker of an output written by :func:`output_dir` (a dict with ``command``), or None."""
    try:
        marker = json.loads((Path(path) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return marker if isinstance(marker, dict) and isinstance(marker.get("command"), str) else None


def _files(root: Path) -> list[str]:
    """Every file and link below ``root`` (relative POSIX paths, sorted); empty folders as ``name/``."""
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        rel = Path(dirpath).relative_to(root)
        out += [(rel / f).as_posix() for f in filenames]
        out += [(rel / d).as_posix() for d in dirnames if (Path(dirpath) / d).is_symlink()]
        if not dirnames and not filenames and rel != Path("."):
            out.append(rel.as_posix() + "/")
    return sorted(out)


def _foreign(out: Path, marker: dict[str, Any] | None) -> list[str]:
    """Files in ``out`` that its marker does not list (all of them without a marker)."""
    present = _files(out)
    if marker is None:
        return present
    listed = marker.get("files")
    if not isinstance(listed, list):
        return []  # a marker of a version before the file list: all of it was written by lfstudy
    ours = {*listed, MARKER}
    parents = {p.rsplit("/", 1)[0] + "/" for p in ours if "/" in p}
    return [p for p in present if p not in ours and not (p.endswith("/") and p in parents)]


def _named(files: list[str], limit: int = 3) -> str:
    shown = ", ".join(repr(f) for f in files[:limit])
    return shown + (f" and {len(files) - limit} more" if len(files) > limit else "")


def check_output(path: str | Path, *, command: str, inputs: Iterable[str | Path] = (), overwrite: bool = False) -> Path:
    """Check that a command may write its output directory ``path``; return it resolved.

    A new path is fine, and so is an empty directory. An existing one is replaced
    only when it carries the marker of an earlier output of the same ``command``,
    holds nothing but the files that marker lists, and ``overwrite`` is given:
    lfstudy never removes data it did not write. A path that is, holds or lies
    inside an input of the run is refused always. The folder that will hold the
    output is created and must be writable.

    Raises
    ------
    OutputError
        One line saying why, and what to do instead.
    """
    shown = str(path)
    out = Path(path).expanduser().resolve()
    if out.parent == out:
        raise OutputError(f"--out {shown!r} is the root of the file system; name a new directory")
    for inp in inputs:
        r = Path(inp).expanduser().resolve()
        if r == out or out in r.parents:
            raise OutputError(f"--out {shown!r} holds {str(r)!r}, an input of this run; choose another --out")
        if r in out.parents:
            raise OutputError(f"--out {shown!r} lies inside {str(r)!r}, an input of this run; choose another --out")
    if out.is_symlink() or out.exists():
        if not out.is_dir():
            raise OutputError(
                f"--out {shown!r} is an existing file; lfstudy {command} writes a directory and replaces no file: "
                "choose another --out"
            )
        _check_existing(out, shown, command, overwrite)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"--out {shown!r}: cannot create {str(out.parent)!r} ({exc.strerror})") from None
    if not os.access(out.parent, os.W_OK | os.X_OK):
        raise OutputError(f"--out {shown!r}: the folder {str(out.parent)!r} is not writable (permission denied)")
    return out


def _check_existing(out: Path, shown: str, command: str, overwrite: bool, *, now: str = "") -> None:
    """Refuse an existing directory at ``out`` unless it is empty, or an earlier output of ``command``
    holding only its own files and ``overwrite`` is given. ``now``: the wording at the swap."""
    if not any(out.iterdir()):
        return
    marker = output_marker(out)
    if marker is None or marker["command"] != command:
        what = "no lfstudy output" if marker is None else f"an output of lfstudy {marker['command']}"
        raise OutputError(
            f"--out {shown!r} {now or 'exists and '}is {what} (no {MARKER} of lfstudy {command}); lfstudy never "
            "replaces data it did not write: choose a new --out, or move that directory away yourself"
        )
    foreign = _foreign(out, marker)
    if foreign:
        raise OutputError(
            f"--out {shown!r} {now or ''}holds files lfstudy did not write: {_named(foreign)}; --overwrite replaces "
            "only what lfstudy wrote: move them out of it, or choose a new --out"
        )
    if not overwrite:
        raise OutputError(
            f"--out {shown!r} holds an earlier output of lfstudy {command}; give --overwrite to replace it, "
            "or choose a new --out"
        )


def _probe_move(out: Path, shown: str) -> None:
    """Move an existing ``out`` aside and back: one that cannot be moved (immutable, a mount point)
    fails here, before any processing, not at the swap."""
    if not (out.exists() or out.is_symlink()):
        return
    probe = _sibling(out, "probe")
    try:
        os.replace(out, probe)
    except OSError as exc:
        raise OutputError(
            f"--out {shown!r} cannot be replaced: moving it failed ({exc.strerror}); choose another --out"
        ) from None
    os.replace(probe, out)


@contextmanager
def _output_lock(out: Path, shown: str) -> Iterator[None]:
    """Hold an exclusive lock on ``.NAME.lfstudy-lock`` beside ``out``; a second writer is refused at once.

    The file carries our signature: a file of that name that is not our lock is refused and left alone.
    """
    import fcntl

    lock = out.with_name(f".{out.name}.lfstudy-lock")
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as exc:
            raise OutputError(f"--out {shown!r}: cannot write to {str(out.parent)!r} ({exc.strerror})") from None
        content = os.pread(fd, len(_SIGNATURE) + 1, 0)
        if content not in (b"", _SIGNATURE):
            os.close(fd)
            raise OutputError(
                f"--out {shown!r}: {str(lock)!r} exists and is not an lfstudy lock; move it away, or choose another "
                "--out"
            )
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise OutputError(
                f"--out {shown!r} is being written by another lfstudy run (lock {str(lock)!r}); wait for it to "
                "finish or choose another --out"
            ) from None
        try:
            if os.fstat(fd).st_ino == os.stat(lock).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)  # the run that held it removed it meanwhile: lock the file now there
    try:
        if not content:
            os.pwrite(fd, _SIGNATURE, 0)
        yield
    finally:
        with suppress(OSError):
            lock.unlink()  # while still held: a waiting run then locks a fresh file (checked above)
        os.close(fd)


@contextmanager
def output_dir(
    path: str | Path, *, command: str, inputs: Iterable[str | Path] = (), overwrite: bool = False
) -> Iterator[Path]:
    """A command's output directory, written safely: yield an empty temporary directory beside it,
    on success mark it and move it into place.

    The checks of :func:`check_output` run first, under an exclusive lock on the
    output (a second run writing the same output is refused), an existing output is
    moved aside and back (one that cannot be replaced fails now), and the temporary
    directory is made before the caller's work, so an unwritable output fails before
    any processing. At the swap the existing output is checked again: a file put into
    it meanwhile makes the run fail with the file named, and the directory is left as
    it was. On an exception nothing is left behind and ``path`` is as it was.

    Parameters
    ----------
    path : path
        The output directory (or zarr store).
    command : str
        The command writing it; recorded in its :data:`MARKER` with the files written.
    inputs : paths
        Files and stores the run reads: the output may not be, hold or lie inside one.
    overwrite : bool
        Replace an earlier output of the same command (only what it wrote).

    Raises
    ------
    OutputError
        The output may not be written (one line: why, and what to do).
    """
    shown = str(path)
    inputs = [str(p) for p in inputs]
    out = check_output(path, command=command, inputs=inputs, overwrite=overwrite)
    with _output_lock(out, shown):
        clear_stale(out)
        check_output(path, command=command, inputs=inputs, overwrite=overwrite)  # as it is now, under the lock
        _probe_move(out, shown)
        tmp = _sibling(out, "tmp")
        try:
            tmp.mkdir()
        except OSError as exc:
            raise OutputError(f"--out {shown!r}: cannot write to {str(out.parent)!r} ({exc.strerror})") from None
        try:
            yield tmp
            from lfstudy import __version__

            marker = {
                "command": command,
                "lfstudy_version": __version__,
                "created": datetime.now(UTC).isoformat(timespec="seconds"),
                "inputs": inputs,
                "files": _files(tmp),
            }
            (tmp / MARKER).write_text(json.dumps(marker, indent=1) + "\n")

            def still_ours(parked: Path) -> None:
                if parked.is_symlink() or not parked.is_dir():
                    raise OutputError(f"--out {shown!r} became a file while this run wrote; it is left as it was")
                _check_existing(parked, shown, command, overwrite, now="now ")

            _swap(tmp, out, still_ours)
        finally:
            if tmp.exists():
                _remove(tmp)
