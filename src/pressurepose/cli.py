"""`pressurepose` command line: one subcommand per pipeline stage, each a function of
`pressurepose.commands` (its config, its run, its files and its one-line summary).

User errors (`pressurepose.errors.UserError`: bad input, bad files, a config value its
dataclass's `__post_init__` refuses, a flag's text that is not of its type; OSError: missing,
unreadable or unwritable files) print one line and exit with status 2; anything else is a bug
and keeps its traceback, also when tyro meets it while building the configs (`_argument_error`).
"""

from __future__ import annotations

import contextlib
import logging
import sys

import tyro

from pressurepose.commands.calibrate import calibrate
from pressurepose.commands.compare import compare
from pressurepose.commands.coregister import coregister
from pressurepose.commands.demo import demo
from pressurepose.commands.evaluate import evaluate
from pressurepose.commands.evaluate_real import evaluate_real
from pressurepose.commands.generate import generate
from pressurepose.commands.imports import import_original, import_pmatdata, import_pressurepose_real, import_slp
from pressurepose.commands.info import info
from pressurepose.commands.pose import pose
from pressurepose.commands.predict import predict
from pressurepose.commands.realism import realism
from pressurepose.commands.sample import sample
from pressurepose.commands.simulate import simulate
from pressurepose.commands.train import train
from pressurepose.commands.view import cache, click, view
from pressurepose.errors import UserError

COMMANDS = {
    "demo": demo,
    "pose": pose,
    "sample": sample,
    "simulate": simulate,
    "generate": generate,
    "info": info,
    "import-original": import_original,
    "import-pmatdata": import_pmatdata,
    "import-pressurepose-real": import_pressurepose_real,
    "import-slp": import_slp,
    "calibrate": calibrate,
    "coregister": coregister,
    "click": click,
    "cache": cache,
    "realism": realism,
    "train": train,
    "predict": predict,
    "evaluate": evaluate,
    "evaluate-real": evaluate_real,
    "compare": compare,
    "view": view,
}


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
        run = tyro.extras.subcommand_cli_from_dict(
            COMMANDS, prog="pressurepose", args=argv, config=(tyro.conf.OmitArgPrefixes,)
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
