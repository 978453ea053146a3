"""A user's own code named in the config (`package.module:name`: env ids, env wrappers, encoders),
imported with the current directory on the import path, or one line that says what was tried."""

from __future__ import annotations

import difflib
import importlib
import inspect
import os
import sys
import traceback
from collections.abc import Callable
from typing import Any

from relayrl.errors import UserError


def import_user_module(module_name: str, what: str) -> Any:
    """Import a user's module, or fail in one line that says what was tried and how to fix it."""
    try:
        try:
            return importlib.import_module(module_name)
        except ModuleNotFoundError as e:
            # A script run from a subfolder has that folder on the path, not the current one: the
            # current one is tried last, as the CLI puts it (last: no library finds its modules there).
            if e.name != module_name.split(".")[0] or "" in sys.path or os.getcwd() in sys.path:
                raise
            sys.path.append(os.getcwd())
            return importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if e.name is None or not module_name.startswith(e.name):
            raise UserError(f"{what}: importing {module_name!r} failed: it imports {e.name!r}, which is "
                            "not installed") from None
        parent, _, leaf = e.name.rpartition(".")
        if parent and (found := sys.modules.get(parent)) is not None:  # the package is there, the module not
            folders = list(getattr(found, "__path__", []))
            if not folders:  # mygame.py, not a folder mygame/: nothing can be inside it
                raise UserError(f"{what}: {parent!r} ({getattr(found, '__file__', '?')}) is a module, not a package "
                                f"with modules in it: name what it defines as {parent}:Name") from None
            raise UserError(f"{what}: package {parent!r} ({folders[0]}) has no module {leaf!r}") from None
        top = e.name.split(".")[0]
        raise UserError(
            f"{what}: no module {e.name!r} in the current directory ({os.getcwd()}) or the installed "
            f"packages; run relayrl from the folder that holds {top}.py (or {top}/), add that folder "
            "to PYTHONPATH, or pip install -e your project") from None
    except Exception as e:  # the user's module raised while it was imported
        raise UserError(f"{what}: importing {module_name!r} raised {type(e).__name__}: {e}{_place(e)}") from None


def _place(e: Exception) -> str:
    """" (file:line)" of the user's code that raised: the last frame outside importlib's frozen
    ones; "" for a SyntaxError (its message names the file and line; its traceback ends in
    importlib's frames) or where no frame is the user's."""
    if isinstance(e, SyntaxError):
        return ""
    frames = [f for f in traceback.extract_tb(e.__traceback__) if not f.filename.startswith("<frozen")]
    return f" ({frames[-1].filename}:{frames[-1].lineno})" if frames else ""


def load_callable(path: str, what: str) -> Callable[..., Any]:
    """`package.module:name` resolved to a callable (env.wrappers, agent.encoder)."""
    if path.count(":") != 1:
        raise UserError(f"{what}: {path!r} is not package.module:Callable")
    module_name, name = path.split(":")
    module = import_user_module(module_name, f"{what}: {path!r}")
    target = getattr(module, name, None)
    if not callable(target):
        raise UserError(f"{what}: {path!r}: module {module_name!r} has no callable {name!r}"
                        f"{near_callable(module, module_name, name)}")
    return target


def bind_error(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> str | None:
    """Why `fn(*args, **kwargs)` cannot bind to fn's parameters (the TypeError's words), or None;
    None too where fn has no signature to read (a builtin: the call itself says)."""
    try:
        inspect.signature(fn).bind(*args, **kwargs)
    except TypeError as e:
        return str(e)
    except ValueError:
        pass
    return None


def near_callable(module: Any, module_name: str, name: str) -> str:
    """"; did you mean module:Name?" for the module's callable nearest `name` (case aside), or ""."""
    names = {n.lower(): n for n, v in vars(module).items() if not n.startswith("_") and callable(v)}
    close = difflib.get_close_matches(name.lower(), list(names), n=1, cutoff=0.6)
    return f"; did you mean {module_name}:{names[close[0]]}?" if close else ""
