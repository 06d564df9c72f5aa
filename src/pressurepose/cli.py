"""`pressurepose` command line: one subcommand per pipeline stage, each a function of
`pressurepose.commands` (its config, its run, its files and its one-line summary).

User errors (`pressurepose.errors.UserError`: bad input, bad files, a config value its
dataclass's `__post_init__` refuses, a flag's text that is not of its type; OSError: missing,
unreadable or unwritable files) print one line and exit with status 2; anything else is a bug
and keeps its traceback, also when tyro meets it while building the configs (`_argument_error`).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import sys
from collections.abc import Callable

import tyro

from pressurepose.errors import UserError

# name -> the command's function, as "module:function" (imported when that command runs, so a
# command pays for its own dependencies only: `pressurepose info` 6.8 -> 2.4 s on the project
# machine; `--help` and unknown names import them all) or the function itself.
COMMANDS: dict[str, str | Callable] = {
    "demo": "demo:demo",
    "pose": "pose:pose",
    "sample": "sample:sample",
    "simulate": "simulate:simulate",
    "generate": "generate:generate",
    "info": "info:info",
    "import-original": "imports:import_original",
    "import-pmatdata": "imports:import_pmatdata",
    "import-pressurepose-real": "imports:import_pressurepose_real",
    "import-slp": "imports:import_slp",
    "calibrate": "calibrate:calibrate",
    "coregister": "coregister:coregister",
    "click": "view:click",
    "cache": "view:cache",
    "realism": "realism:realism",
    "train": "train:train",
    "predict": "predict:predict",
    "evaluate": "evaluate:evaluate",
    "evaluate-real": "evaluate_real:evaluate_real",
    "compare": "compare:compare",
    "view": "view:view",
}


def _function(spec: str | Callable) -> Callable:
    if callable(spec):
        return spec
    module, name = spec.split(":")
    return getattr(importlib.import_module(f"pressurepose.commands.{module}"), name)


def commands_for(argv: list[str]) -> dict[str, Callable]:
    """The commands tyro is shown: only the one named first in argv, else (help, a typo) all."""
    names = [argv[0]] if argv and argv[0] in COMMANDS else list(COMMANDS)
    return {name: _function(COMMANDS[name]) for name in names}


def _argument_error(event) -> None:
    """tyro's parse-error hook, for a value that tyro parsed but could not build a config from.

    tyro turns every ValueError raised while building the configs (a field's type conversion,
    a config's `__post_init__`) into its own message box, which would hide a bug's traceback
    and show a user's mistake under tyro's internal field names. Here: a text that does not
    convert to the field's type, or a config's own check (a `UserError`), becomes a
    `UserError` - one line, exit 2; any other exception (a ValueError from inside library
    code is a bug) is raised again as it was, traceback and all. Other parse errors (unknown
    flags, bad choices) keep tyro's usage message, also exit 2."""
    if type(event).__name__ != "InstantiationFailure":
        return
    message = " ".join(str(event.message).split())
    argument = getattr(event, "argument", None)
    if argument is not None:  # the text given for this flag is not of the field's type
        raise UserError(f"{_flag_of(argument)}: {message}")
    cause = _construction_error(sys.exc_info()[1])
    if cause is None:  # tyro's own complaint (e.g. missing arguments)
        raise UserError(message)
    raise cause  # a UserError: one line (`main`); anything else: a bug, with its traceback


def _flag_of(argument) -> str:
    """'--n (expects INT)' for tyro's argument definition, as far as it says."""
    lowered = getattr(argument, "lowered", None)
    flags = "/".join(getattr(lowered, "name_or_flags", None) or ()) or "an argument"
    metavar = getattr(lowered, "metavar", None)
    return f"{flags} (expects {metavar})" if metavar else flags


def _construction_error(exc: BaseException | None) -> BaseException | None:
    """The exception a config's construction raised, under tyro's InstantiationError wrappers
    (tyro raises them while handling it, so it is their context); None when tyro raised one of
    its own (missing arguments) or the hook runs outside tyro's handler."""
    while exc is not None and type(exc).__name__ == "InstantiationError":
        exc = exc.__cause__ or exc.__context__
    return exc


def _parse_and_run(argv: list[str] | None) -> None:
    hook = getattr(getattr(tyro, "_errors", None), "on_parse_error", None)
    context = hook(_argument_error) if hook is not None else contextlib.nullcontext()
    with context:
        args = sys.argv[1:] if argv is None else argv
        run = tyro.extras.subcommand_cli_from_dict(
            commands_for(args), prog="pressurepose", args=args, config=(tyro.conf.OmitArgPrefixes,)
        )
    return run


def describe_os_error(exc: OSError) -> str:
    """One line for a missing, unreadable or unwritable file, naming it."""
    if exc.filename is None or exc.strerror is None:
        return str(exc)
    where = f"{exc.filename}" + (f" -> {exc.filename2}" if exc.filename2 else "")
    return f"{where}: {exc.strerror.lower()}"


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        _parse_and_run(argv)
    except UserError as exc:
        # Our input checks raise UserError naming the file, the field and what was expected.
        print(f"pressurepose: error: {' '.join(str(exc).split())}", file=sys.stderr)  # one line
        return 2
    except OSError as exc:
        # Unreadable, unwritable or missing files: not a bug either.
        print(f"pressurepose: error: {describe_os_error(exc)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
