"""A user's source checkout of an encoder's code (NVlabs/FoundationStereo, NVlabs/Fast-FoundationStereo), imported
pinned to that checkout and built offline.

Their code imports itself by top-level names that the two checkouts share (``core``, ``Utils``; FoundationStereo's
``core/`` has no ``__init__.py``, so Python would merge or replace it with another ``core`` found anywhere on
``sys.path``). ``Checkout(root).active()`` makes one checkout the only provider of its names for the duration of a
``with`` block: the names it provides (its top-level ``*.py`` files and folders holding Python files) are taken out
of ``sys.modules`` and found only in the checkout (a finder first on ``sys.meta_path`` searches the ``sys.path``
entries inside the checkout for them, so ``torch.hub``'s own entry for a vendored repository counts); this
checkout's own modules from an earlier block are put back. On leaving, every module loaded from the checkout
(aliases such as Fast-FoundationStereo's ``foundation_stereo_ori`` included) is kept with the ``Checkout`` and
removed again, and ``sys.modules``, ``sys.path`` and the root logger's level and handlers are restored. Models built
inside keep working afterwards: their classes hold their own module globals, and neither repository imports
anything at run time. Blocks are serialised by a lock and must not nest.

``offline(root)`` is the network guarantee while their modules are built or unpickled: Python sockets may not
resolve or connect (an attempt raises ``OfflineError`` and is remembered), ``torch.hub.load('owner/name', ...)``
is served from the checkout's vendored ``<root>/<name>/hubconf.py`` (FoundationStereo vendors ``dinov2/``) and
``timm.create_model`` builds with ``pretrained=False``: every weight comes from the user's checkpoint.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.abc
import importlib.machinery
import logging
import socket
import sys
import threading
from pathlib import Path
from types import ModuleType

import torch

from sgmodel.weights import WeightsError

#: pip distributions of import names that differ from them (for the "install ..." message).
PIP_NAMES = {"cv2": "opencv-contrib-python-headless", "skimage": "scikit-image", "yaml": "pyyaml", "PIL": "pillow",
             "sklearn": "scikit-learn"}
_LOCK = threading.RLock()


class OfflineError(OSError):
    """A network access attempted while an encoder was being built."""


def one_line(e: BaseException) -> str:
    """``Type: first line of the message`` of an exception, for one-line errors."""
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0]}" if text else type(e).__name__


class Checkout:
    """One source checkout at ``root`` (the folder holding ``core/``), its modules pinned to it."""

    def __init__(self, root: str | Path, project: str) -> None:
        self.root = Path(root).resolve()
        self.project = project
        self.names = provided_names(self.root)
        self.modules: dict[str, ModuleType] = {}

    def owns(self, module: object) -> bool:
        """Whether ``module`` was loaded from a file (or, for a namespace package, a folder) inside the checkout."""
        try:
            places = [getattr(module, "__file__", None)] + list(getattr(module, "__path__", None) or [])
        except (TypeError, KeyError):  # module-like objects with unusual __path__s (torch._classes)
            return False
        return any(isinstance(p, str) and _inside(Path(p), self.root) for p in places)

    @contextlib.contextmanager
    def active(self):
        """Inside the block, ``import core...`` (and every other name the checkout provides) means this checkout."""
        with _LOCK:
            saved_path, saved_logging = list(sys.path), (logging.root.level, list(logging.root.handlers))
            saved = {n: sys.modules.pop(n) for n in list(sys.modules) if n.split(".")[0] in self.names}
            sys.modules.update(self.modules)
            sys.path.insert(0, str(self.root))
            finder = _CheckoutFinder(self)
            sys.meta_path.insert(0, finder)
            try:
                yield self
            finally:
                sys.meta_path.remove(finder)
                owned = {name: m for name, m in list(sys.modules.items()) if self.owns(m)}
                for name in [n for n in sys.modules if n in owned or n.split(".")[0] in self.names]:
                    del sys.modules[name]
                self.modules.update(owned)
                sys.modules.update(saved)
                sys.path[:] = saved_path
                # FoundationStereo's Utils.py reconfigures logging when imported (reload, INFO to stderr)
                logging.root.setLevel(saved_logging[0])
                logging.root.handlers[:] = saved_logging[1]

    @contextlib.contextmanager
    def building(self, flag: str):
        """``active()`` and ``offline()`` together: import, build or unpickle the checkout's models inside."""
        with self.active(), offline(self.root, flag, self.project):
            yield self

    def import_module(self, name: str, flag: str) -> ModuleType:
        """``name`` from the checkout (call inside ``active()``); a WeightsError naming ``flag`` if that fails."""
        try:
            return importlib.import_module(name)
        except Exception as e:  # noqa: BLE001 - anything their modules raise on import is one user error
            missing = (e.name or "").split(".")[0] if isinstance(e, ModuleNotFoundError) else ""
            if missing and missing not in self.names:
                pip = PIP_NAMES.get(missing, missing)
                raise WeightsError(f"{flag} {self.root}: NVlabs/{self.project} needs the Python package '{pip}', "
                                   f"which is not installed here (pip install {pip}; docs/encoders.md lists what to "
                                   f"install)") from e
            package = self._failing_package(e)
            if package:
                raise WeightsError(f"{flag} {self.root}: NVlabs/{self.project} imports '{package}', which fails to "
                                   f"load here ({one_line(e)}; docs/encoders.md lists what to install)") from e
            raise WeightsError(f"{flag} {self.root}: importing {name} failed ({one_line(e)}); is it a checkout of "
                               f"NVlabs/{self.project}?") from e

    def _failing_package(self, e: BaseException) -> str | None:
        """The top-level package outside the checkout in which ``e`` was raised, if it was raised outside."""
        tb = e.__traceback__
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        if tb is None or _inside(Path(tb.tb_frame.f_code.co_filename), self.root):
            return None
        file = Path(tb.tb_frame.f_code.co_filename).resolve()
        entries = [Path(p).resolve() for p in sys.path if p and _inside(file, Path(p))]
        if not entries:  # not a file on sys.path (importlib's own frames)
            return None
        return file.relative_to(max(entries, key=lambda p: len(p.parts))).parts[0].removesuffix(".py")


class _CheckoutFinder(importlib.abc.MetaPathFinder):
    """Finds the checkout's top-level names in the ``sys.path`` entries inside the checkout, and only there."""

    def __init__(self, checkout: Checkout) -> None:
        self.checkout = checkout

    def find_spec(self, fullname: str, path=None, target=None):
        if "." in fullname or fullname not in self.checkout.names:
            return None
        entries = [p for p in sys.path if _inside(Path(p or "."), self.checkout.root)]
        return importlib.machinery.PathFinder.find_spec(fullname, entries)


def provided_names(root: Path) -> set[str]:
    """Top-level import names a checkout provides: its ``*.py`` files and the folders that hold Python files."""
    names = {p.stem for p in root.glob("*.py")}
    names |= {p.name for p in root.iterdir() if p.is_dir() and p.name.isidentifier() and any(p.glob("*.py"))}
    return names


def _inside(path: Path, root: Path) -> bool:
    try:
        return path.resolve().is_relative_to(root)
    except OSError:
        return False


@contextlib.contextmanager
def offline(root: Path, flag: str, project: str):
    """No network while a checkout's modules are built or loaded (see the module docstring). A failure inside
    that follows a blocked network attempt becomes a WeightsError saying what was reached for."""
    attempts: list[str] = []
    getaddrinfo, connect, hub_load = socket.getaddrinfo, socket.socket.connect, torch.hub.load

    def refuse(what: str):
        attempts.append(what)
        raise OfflineError(f"network access to {what} refused: sgmodel builds encoders offline")

    def guarded_getaddrinfo(host, port, *args, **kwargs):
        refuse(f"{host}:{port}")

    def guarded_connect(sock, address):
        if sock.family in (socket.AF_INET, socket.AF_INET6):
            refuse(f"{address[0]}:{address[1]}")
        return connect(sock, address)

    def local_hub(repo_or_dir, model, *args, source="github", **kwargs):
        if source == "local":
            return hub_load(repo_or_dir, model, *args, source="local", **kwargs)
        name = str(repo_or_dir).split(":")[0].split("/")[-1]
        vendored = root / name
        if not (vendored / "hubconf.py").is_file():
            raise WeightsError(f"{flag} {root}: NVlabs/{project} loads {repo_or_dir} through torch.hub, and the "
                               f"checkout has no {name}/hubconf.py to load it from offline (use a complete checkout)")
        kwargs.pop("force_reload", None), kwargs.pop("skip_validation", None), kwargs.pop("trust_repo", None)
        return hub_load(str(vendored), model, *args, source="local", **kwargs)

    timm = _import_optional("timm")
    create_model = getattr(timm, "create_model", None)
    socket.getaddrinfo, socket.socket.connect, torch.hub.load = guarded_getaddrinfo, guarded_connect, local_hub
    if create_model is not None:
        timm.create_model = lambda *a, **k: create_model(*a, **{**k, "pretrained": False})
    try:
        yield
    except WeightsError:
        raise
    except Exception as e:
        if attempts:
            raise WeightsError(f"{flag} {root}: building NVlabs/{project} reached for the network ({attempts[0]}); "
                               f"sgmodel builds it offline, every weight from --encoder-weights ({one_line(e)})") from e
        raise
    finally:
        socket.getaddrinfo, socket.socket.connect, torch.hub.load = getaddrinfo, connect, hub_load
        if create_model is not None:
            timm.create_model = create_model


def _import_optional(name: str) -> ModuleType | None:
    try:
        return importlib.import_module(name)
    except ImportError:
        return None
