"""One error path for every script: bad input ends in one line on stderr."""

import contextlib
import errno
import logging
import os
import shutil
import sys
import traceback
from collections.abc import Callable, Iterator
from typing import Any, NoReturn

from absl import app
from absl import flags
from ml_collections import config_flags

from clipgs_jax import config as config_lib

# Exit status of a run stopped by bad input (a file, a value, the disk).
EXIT_ERROR = 1
# Exit status of a command line that could not be parsed or made no sense
# (the shell convention for usage errors).
EXIT_USAGE = 2
# Errors raised at the library's boundary that carry a message written for
# the user (what, where, the fix). Anything else is a bug: it keeps its
# traceback.
USER_ERRORS = (ValueError, OSError, FloatingPointError, app.UsageError)
# What to do about an OSError without a message of our own, by errno.
_OS_FIXES = {
    errno.ENOSPC: "free space on that disk or choose another --workdir",
    errno.EDQUOT: "free space on that disk or choose another --workdir",
    errno.EACCES: "check the file's permissions (chmod) and owner",
    errno.EPERM: "check the file's permissions (chmod) and owner",
    errno.EROFS: "choose a writable --workdir",
    errno.ENOENT: "check the path",
    errno.EISDIR: "pass a file, not a folder",
    errno.ENOTDIR: "pass a folder, not a file",
}
_DEBUG_FLAG = "debug"
_DEBUG_ALIAS = "verbose"
# JAX logs the accelerator backends it could not start ("Unable to
# initialize backend 'tpu'") when a script first touches a device: a note
# about the machine, not the run, and the first line a user would read.
# Shown with --debug or an explicit --verbosity.
_BACKEND_LOGGER = "jax._src.xla_bridge"


def error_line(e: BaseException) -> str:
  """The single line that reports `e`: 'error: <what>, <where>, <fix>'.

  Library messages already name the file or argument and the fix; an
  OSError from the system (no message of ours) gets its path and a fix by
  errno. Newlines are folded, so the report stays one line.
  """
  if isinstance(e, OSError) and e.filename is not None and e.strerror:
    fix = _OS_FIXES.get(e.errno, "check the path and retry")
    text = f"{e.strerror}: {e.filename}; {fix}"
  else:
    text = str(e) or type(e).__name__
  text = " ".join(text.split())
  return f"error: {text}"


def _debug() -> bool:
  """--debug/--verbose, or $CLIPGS_DEBUG (for errors before parsing)."""
  if os.environ.get("CLIPGS_DEBUG"):
    return True
  try:
    return bool(flags.FLAGS[_DEBUG_FLAG].value)
  except (KeyError, flags.UnparsedFlagAccessError):
    return False


def report(e: BaseException, code: int = EXIT_ERROR) -> NoReturn:
  """Prints e's one line (after its traceback with --debug) and exits."""
  if _debug():
    traceback.print_exception(e)
  sys.stdout.flush()
  print(error_line(e), file=sys.stderr, flush=True)
  sys.exit(code)


def guarded(main: Callable[[list[str]], Any]) -> Callable[[list[str]], Any]:
  """main(argv) whose user errors end in one stderr line and an exit code.

  app.UsageError exits with EXIT_USAGE, without absl's help dump (--help
  still prints it); ValueError, OSError (FileNotFoundError,
  PermissionError, disk full) and FloatingPointError exit with EXIT_ERROR.
  Other exceptions are bugs and keep their traceback.
  """
  def wrapped(argv):
    _quiet_backend_notices()
    try:
      return main(argv)
    except app.UsageError as e:
      report(e, EXIT_USAGE)
    except USER_ERRORS as e:
      report(e, EXIT_ERROR)
  return wrapped


def _quiet_backend_notices() -> None:
  """Hides JAX's backend notices unless --debug or --verbosity is given."""
  verbosity = "verbosity" in flags.FLAGS and flags.FLAGS["verbosity"].present
  level = logging.NOTSET if _debug() or verbosity else logging.ERROR
  logging.getLogger(_BACKEND_LOGGER).setLevel(level)


def _parse_flags(argv: list[str]) -> list[str]:
  """absl's flag parsing, with a parse error as one line (no help hint)."""
  try:
    return flags.FLAGS(argv)
  except flags.Error as e:
    if os.environ.get("CLIPGS_DEBUG"):
      traceback.print_exception(e)
    print(f"error: {' '.join(str(e).split())}; see --helpshort",
          file=sys.stderr, flush=True)
    sys.exit(EXIT_USAGE)


def _define_debug_flag() -> None:
  # Defined when a script starts, never at import: the library defines no
  # flags (importing it twice must not raise duplicate-flag errors).
  if _DEBUG_FLAG not in flags.FLAGS:
    flags.DEFINE_bool(_DEBUG_FLAG, False,
                      "On an error, print the traceback before its line.")
    flags.DEFINE_alias(_DEBUG_ALIAS, _DEBUG_FLAG)


def run(main: Callable[[list[str]], Any],
        argv: list[str] | None = None) -> None:
  """app.run(main) for scripts: flags, then main under `guarded`.

  Adds --debug (alias --verbose) to show tracebacks.

  Args:
    main: the script's main(argv).
    argv: the command line, default sys.argv.
  """
  _define_debug_flag()
  app.run(guarded(main), argv=argv, flags_parser=_parse_flags)


def no_arguments(argv: list[str]) -> None:
  """Raises UsageError for positional arguments (scripts take flags only)."""
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}; every input is a "
                         "--flag=value (see --helpshort)")


def require(ok: bool, flag: str, value: Any, fix: str) -> None:
  """Raises UsageError '--flag=value <fix>' unless `ok`.

  For checks of flag values that need no file: run them all before any
  scene or weights are loaded.
  """
  if not ok:
    raise app.UsageError(f"--{flag}={value} {fix}")


def require_folder(flag: str, path: str | None) -> None:
  """Raises FileNotFoundError unless `path` (given by --flag) is a folder."""
  if path is None:
    return
  if not os.path.isdir(path):
    what = "is a file" if os.path.exists(path) else "does not exist"
    raise FileNotFoundError(f"--{flag}={path} {what}; pass an existing "
                            "folder")


def require_file(flag: str, path: str | None) -> None:
  """Raises FileNotFoundError unless `path` (given by --flag) exists."""
  if path is not None and not os.path.exists(path):
    raise FileNotFoundError(f"--{flag}={path} does not exist; check the "
                            "path")


@contextlib.contextmanager
def output_dir(path: str, keep: str | None = None) -> Iterator[str]:
  """Creates the output folder `path`; a failed run leaves nothing behind.

  If the block raises before `keep` (a file name inside `path`, e.g. the
  first checkpoint) exists, what the block created goes away: the whole
  folder if it did not exist before, otherwise the entries that were not
  there before. With `keep` present the folder stays, so that a long run
  that fails late can still be resumed.

  Args:
    path: str, the folder (--workdir).
    keep: str or None, the file whose presence marks work worth keeping.

  Yields:
    The absolute path.
  """
  path = os.path.abspath(path)
  if os.path.exists(path) and not os.path.isdir(path):
    raise ValueError(f"output folder {path} is a file; pass a new or "
                     "existing folder")
  existed = os.path.isdir(path)
  before = set(os.listdir(path)) if existed else set()
  os.makedirs(path, exist_ok=True)
  try:
    yield path
  except BaseException:
    if keep is None or not os.path.exists(os.path.join(path, keep)):
      if not existed:
        shutil.rmtree(path, ignore_errors=True)
      else:
        for name in set(os.listdir(path)) - before:
          entry = os.path.join(path, name)
          if os.path.isdir(entry) and not os.path.islink(entry):
            shutil.rmtree(entry, ignore_errors=True)
          else:
            os.remove(entry)
    raise


def define_config_file(name: str, default: str, help_text: str):
  """config_flags.DEFINE_config_file, with a bad override as one line.

  ml_collections reads the --NAME.FIELD=VALUE overrides while the flag is
  defined (at import), so an unknown field fails there: it exits with
  EXIT_USAGE and one line naming the field, like any other flag error (a
  field that moved, config.RENAMED, with its new name).
  """
  prefix = f"--{name}."
  for arg in sys.argv[1:]:
    key = arg[len(prefix):].split("=", 1)[0] if arg.startswith(prefix) else ""
    if key in config_lib.RENAMED:
      report(app.UsageError(f"{prefix}{key} is now {prefix}"
                            f"{config_lib.RENAMED[key]}; use the new name"),
             EXIT_USAGE)
  try:
    return config_flags.DEFINE_config_file(name, default, help_text,
                                           lock_config=True)
  except (AttributeError, KeyError, TypeError, ValueError) as e:
    text = str(e).replace("\\n", " ").replace("\\'", "").strip("'\"")
    report(app.UsageError(f"--{name}: no such field or a bad override "
                          f"({' '.join(text.split())}); the fields are in "
                          f"{default}"), EXIT_USAGE)
