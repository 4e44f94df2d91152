"""One registry type for every backend chosen by URL: I2C buses, PWM outputs, MAVLink links.

Crazyflie's `cflib.crtp.get_link_driver(uri)` is the model: the URL's scheme picks a factory, the
factory gets the whole URL and reads its own options after the scheme. One rule set, whatever is
being opened:

- A scheme is lower-case ASCII (RFC 3986's letters, digits, '+', '.', '-', a letter first).
- Built-ins are the module's own backends (smbus2, the device bridge, sysfs PWM, pymavlink ...):
  listed first and never replaced or removed, so a layer registering `tcp` cannot silently take the
  device bridge's place.
- Other layers (the SITL, tests) register more schemes at run time, so firmware_py never imports
  them; registering a scheme again replaces it, unregistering an unknown one does nothing.
- An unknown scheme is one ValueError naming the URL and listing every scheme known.
- A credential (the device bridge's `key`, a MAVLink link's `signing`) goes, as that keyword, to the
  factories that take it (read from the factory's signature once, at registration). A factory that
  does not take it is either given none (`Credential.OPTIONAL`: a local bus has no link to
  authenticate) or refused (`Credential.REQUIRED`: an unsigned link where signing was asked for).
- Built-ins may also take the module's own options (the PWM output's I2C opener and MAVLink link,
  the MAVLink source ids); registered factories get only the URL and the credential.

`check(url)` refuses a malformed URL without opening anything, so a program can check all its
options before it touches the hardware: built-ins run their parser, a registered scheme is checked
when it is opened.
"""

from __future__ import annotations

import enum
import inspect
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

T = TypeVar("T")

SCHEME_RE = re.compile(r"[a-z][a-z0-9+.-]*", re.ASCII)
"""What a scheme may be (RFC 3986, lower case only)."""


class Credential(enum.Enum):
    """What a backend that cannot use the caller's credential does with it."""

    OPTIONAL = "optional"  # opened without it (the key authenticates the device bridge only)
    REQUIRED = "required"  # refused: the caller asked for an authenticated link


@dataclass(frozen=True, slots=True)
class Backend(Generic[T]):
    """One scheme's factory, and what it takes."""

    scheme: str
    factory: Callable[..., T]
    builtin: bool
    takes_credential: bool
    check: Callable[[str], object] | None = None
    """A built-in's parser: raises ValueError for a malformed URL, opens nothing."""


class BackendRegistry(Generic[T]):
    """Scheme -> factory for one kind of backend (module docstring).

    Args:
        kind: what is opened, for messages ("I2C bus", "PWM output", "MAVLink link").
        prefix: what every URL starts with before the scheme ("pwm:" for `pwm:sysfs:0:0`), or "".
        credential: the keyword the credential is passed as ("key", "signing").
        policy: what a backend that cannot take the credential does with it.
        unknown: the unknown-scheme message, formatted with url and scheme (the list of known schemes,
            and `expected`, are appended).
        expected: the URL forms, appended to the unknown-scheme message.
    """

    def __init__(self, kind: str, *, prefix: str = "", credential: str = "key",
                 policy: Credential = Credential.OPTIONAL, unknown: str = "unknown {kind} scheme {scheme!r} in {url!r}",
                 expected: str = "") -> None:
        self.kind, self.prefix, self.credential, self.policy = kind, prefix, credential, policy
        self._unknown, self._expected = unknown, expected
        self._builtins: dict[str, Backend[T]] = {}
        self._registered: dict[str, Backend[T]] = {}

    # ----- registration ----------------------------------------------------------------------------

    def builtin(self, scheme: str, factory: Callable[..., T], *, takes_credential: bool = False,
                check: Callable[[str], object] | None = None) -> None:
        """Declare one of the module's own backends (at import time; never replaced)."""
        self._check_scheme(scheme, factory)
        if scheme in self._builtins:
            raise ValueError(f"{self.kind} built-in scheme {scheme!r} declared twice")
        self._builtins[scheme] = Backend(scheme, factory, True, takes_credential, check)

    def register(self, scheme: str, factory: Callable[..., T]) -> None:
        """Let another layer provide `SCHEME:...` backends (registering a scheme again replaces it)."""
        self._check_scheme(scheme, factory)
        if scheme in self._builtins:
            raise ValueError(f"{self.kind} scheme {scheme!r} is a built-in backend and cannot be replaced")
        self._registered[scheme] = Backend(scheme, factory, False, _takes_keyword(factory, self.credential))

    def unregister(self, scheme: str) -> None:
        """Forget a registered scheme (a SITL run tearing down); unknown schemes are ignored."""
        if scheme in self._builtins:
            raise ValueError(f"{self.kind} scheme {scheme!r} is a built-in backend and cannot be removed")
        self._registered.pop(scheme, None)

    def _check_scheme(self, scheme: object, factory: object) -> None:
        if not isinstance(scheme, str) or not SCHEME_RE.fullmatch(scheme):
            raise ValueError(f"{self.kind} backend scheme must be lower-case letters/digits, a letter first "
                             f"(e.g. 'sitl'), got {scheme!r}")
        if not callable(factory):
            raise ValueError(f"{self.kind} backend factory for {scheme!r} must be callable, got {factory!r}")

    def schemes(self) -> list[str]:
        """Every scheme known, the built-ins first (in declaration order), then the registered ones sorted."""
        return [*self._builtins, *sorted(self._registered)]

    def builtins_only(self) -> BackendRegistry[T]:
        """A copy with the same built-ins and nothing registered (a test's clean slate)."""
        fresh: BackendRegistry[T] = BackendRegistry(
            self.kind, prefix=self.prefix, credential=self.credential, policy=self.policy,
            unknown=self._unknown, expected=self._expected)
        fresh._builtins = dict(self._builtins)
        return fresh

    # ----- lookup ------------------------------------------------------------------------------------

    def scheme_of(self, url: str) -> str:
        """The scheme of a URL (after the prefix, before the first ':'); not checked against the registry."""
        text = url.strip()
        if self.prefix:
            text = text[len(self.prefix):] if text.startswith(self.prefix) else ""
        return text.split(":", 1)[0]

    def backend(self, url: str) -> Backend[T]:
        """The backend a URL's scheme names; ValueError naming the URL and the known schemes otherwise."""
        scheme = self.scheme_of(url)
        found = self._builtins.get(scheme) or self._registered.get(scheme)
        if found is None:
            msg = self._unknown.format(kind=self.kind, url=url, scheme=scheme)
            expected = f"; expected {self._expected}" if self._expected else ""
            raise ValueError(f"{msg} (known: {', '.join(self.schemes())}{expected})")
        return found

    def check(self, url: str) -> Backend[T]:
        """The URL's backend, after its built-in parser accepted the URL (opens nothing)."""
        found = self.backend(url)
        if found.check is not None:
            found.check(url.strip())
        return found

    def open(self, url: str, credential: Any = None, **builtin_options: Any) -> T:
        """Open the backend the URL names (module docstring for the credential and the options)."""
        found = self.backend(url)
        kwargs = dict(builtin_options) if found.builtin else {}
        if credential is not None:
            if found.takes_credential:
                kwargs[self.credential] = credential
            elif self.policy is Credential.REQUIRED:
                raise ValueError(f"{self.kind} backend {found.scheme!r} does not support {self.credential}")
        return found.factory(url.strip(), **kwargs)


def _takes_keyword(fn: Callable[..., Any], name: str) -> bool:
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == name or p.kind is inspect.Parameter.VAR_KEYWORD for p in params)
