"""The commands' output paths, checked before any work: never an input, never one path twice, --force to replace."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.files import path_inside


def _same(a: Path, b: Path) -> bool:
    """True when two paths name one file or folder (symlinks and `..` resolved)."""
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and os.path.samefile(a, b))
    except (OSError, RuntimeError):  # RuntimeError: a symlink loop (Python 3.11)
        return False


def given_paths(*values: str | Path | Iterable[str | Path] | None) -> list[Path]:
    """The input files and folders a command was given, as paths: None skipped, lists flattened, FILE:LABEL cut."""
    paths: list[Path] = []
    for value in values:
        if value is None:
            continue
        for item in [value] if isinstance(value, str | Path) else value:
            text = str(item)
            if not text:  # `--config ""` means no file (Path("") would be the current folder)
                continue
            # a structures argument may be FILE:LABEL; the file is what must not be overwritten
            head, sep, _ = text.rpartition(":")
            paths.append(Path(head if sep and not Path(text).exists() and head else text))
    return paths


def refuse_inputs(
    path: Path, option: str, inputs: Iterable[Path], contains: bool = False, bag_folders: bool = False
) -> None:
    """--force replaces what earlier runs wrote, never what this command reads: an output is no input, lies in no
    input bag folder (`bag_folders`: the inputs are bags) and, for a folder it will replace (`contains`), holds
    no input."""
    for given in inputs:
        if _same(path, given):
            raise InputError(f"{option} {path} is an input of this command; choose another path")
        if bag_folders and given.is_dir() and path_inside(path, given):
            raise InputError(f"{option} {path} is inside {given}, a bag this command reads; choose another path")
        if contains and given.exists() and path_inside(given, path):
            raise InputError(f"{option} {path} holds {given}, an input of this command; choose another path")


def output_file(
    value: str | Path | None,
    force: bool,
    option: str,
    *,
    inputs: Iterable[Path] = (),
    suffixes: tuple[str, ...] = (),
) -> Path | None:
    """A file the command will write: the right suffix, not a folder, not an input, in a folder that exists;
    an existing file only with --force."""
    if not value:
        return None
    path = Path(value)
    if suffixes and path.suffix.lower() not in suffixes:
        raise InputError(f"{option} {path}: use one of {', '.join(suffixes)}")
    if path.is_dir():
        raise InputError(f"{option} {path} is a folder; give a file path")
    refuse_inputs(path, option, inputs)
    if path.exists() and not force:
        raise InputError(f"{path} exists; pass --force to overwrite it")
    if not path.parent.is_dir():
        raise InputError(f"output folder does not exist: {path.parent}")
    if path.is_symlink() and not path.resolve().parent.is_dir():  # checked now, not after the work: a dangling link
        raise InputError(f"{option} {path} links to {path.resolve()}, whose folder does not exist")
    if path.is_symlink() and not force:  # a link to nothing yet is still the user's (a writer may replace it)
        raise InputError(f"{option} {path} is a link to {path.resolve()}; pass --force to write over it")
    if path.exists() and not (path.is_file() or path.is_char_device() or _pipe_with_reader(path)):
        raise InputError(f"{option} {path} is not a regular file (a named pipe or socket would block the write)")
    if not os.access(path if path.exists() else path.parent, os.W_OK):  # now, not after the registration
        raise InputError(f"{option} {path}: {'the file' if path.exists() else 'its folder'} is not writable")
    return path


def _pipe_with_reader(path: Path) -> bool:
    """True for a pipe this process was handed (`-o >(jq .)`, `/dev/stdout` into a pipe): its reader is there.
    A named pipe made with mkfifo is not: with no reader the write blocks forever, and probing one (opening and
    closing it) would end a reader that waits for the first writer's end."""
    return path.is_fifo() and str(path).startswith(("/dev/fd/", "/proc/self/fd/", "/dev/stdout", "/dev/stderr"))


def output_folder(
    value: str | Path | None, option: str, *, inputs: Iterable[Path] = (), bag_folders: bool = False
) -> Path | None:
    """A folder the command writes files into (made if missing): not an existing file, not an input, and
    (`bag_folders`: the inputs are bags) not inside a bag the command reads."""
    if not value:
        return None
    path = Path(value)
    if path.exists() and not path.is_dir():
        raise InputError(f"{option} {path} is a file; give a folder")
    refuse_inputs(path, option, inputs, bag_folders=bag_folders)
    return path


def output_bag(path: Path, force: bool, option: str, inputs: Iterable[Path], bag_folders: bool = False) -> Path:
    """A bag the command will write: never an input nor a folder holding one; an existing one only with --force,
    and only when it is a bag (--force replaces a bag; it never deletes what merely stands at the path)."""
    from liver_p2p_reg.bags.io import check_replaceable_bag

    refuse_inputs(path, option, inputs, contains=True, bag_folders=bag_folders)
    if path.exists() or path.is_symlink():
        if not force:
            raise InputError(f"output bag {path} exists; pass --force to overwrite it")
        check_replaceable_bag(path)
    return path


def distinct_outputs(outputs: dict[str, Iterable[Path | None]]) -> None:
    """Two options never write one path (the second would replace the first's file without a word)."""
    seen: dict[Path, str] = {}
    for option, paths in outputs.items():
        for path in paths:
            if path is None:
                continue
            key = path.resolve()
            if key in seen:
                raise InputError(f"{seen[key]} and {option} would both write {path}; give each its own path")
            seen[key] = option
