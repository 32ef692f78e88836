"""What keeps strangers out of ``perfcap serve``: the pairing token, source allow-lists, and per-client
bounds on message size, message rate and connections, with every refusal counted.

* ``TokenStore``: one pairing token, kept in the state directory (mode 0600) so a phone paired
  yesterday still pairs; ``rotate()`` replaces it, and the old one stops working at once (open
  phone connections that used it are closed by the gateway).
* ``AllowList``: source addresses (hosts or networks) for protocols that cannot carry a token (OSC,
  HyperIMU UDP). Empty means nobody.
* ``RateLimit``: a token bucket; ``RateBook``: buckets by key (a phone's id, a source address) that
  outlive connections, so a client that reconnects finds its bucket as it left it.
* ``Rejections``: counts refusals by reason and logs the first of each reason and then every
  1000th, so a flood is visible without flooding the log.
"""

from __future__ import annotations

import hmac
import ipaddress
import logging
import os
import secrets
import threading
from collections import Counter
from pathlib import Path

from capture.errors import ConfigError

log = logging.getLogger(__name__)

TOKEN_FILE = "pairing-token"


class TokenStore:
    """The pairing token.

    Args:
        state_dir: where the token file lives (created 0700).
        token: use this token instead of the stored one (tests, scripted setups); not stored.
    """

    def __init__(self, state_dir: Path, token: str | None = None) -> None:
        self.path = Path(state_dir) / TOKEN_FILE
        self._lock = threading.Lock()
        self.generation = 0
        if token is not None:
            if len(token) < 16:
                raise ConfigError("a pairing token must be at least 16 characters")
            self._token = token
            self.created = False
            return
        self.created = False
        try:
            text = self.path.read_text(encoding="ascii").strip()
        except FileNotFoundError:
            text = ""
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"cannot read the pairing token {self.path}: {exc}; delete it to make a new one",
                              source=str(self.path)) from None
        if len(text) >= 16:
            self._token = text
        else:
            self._token = self._new()
            self._save()
            self.created = True

    @staticmethod
    def _new() -> str:
        return secrets.token_urlsafe(18)

    def _save(self) -> None:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
            tmp = self.path.with_suffix(".tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w", encoding="ascii") as f:
                f.write(self._token + "\n")
            os.replace(tmp, self.path)
        except OSError as exc:
            raise ConfigError(f"cannot store the pairing token in {self.path}: {exc}", source=str(self.path)) from None

    @property
    def token(self) -> str:
        return self._token

    def check(self, given: str | None) -> bool:
        """Whether ``given`` is the current token (constant-time comparison)."""
        if not given or not isinstance(given, str):
            return False
        return hmac.compare_digest(given.encode("utf-8", "replace"), self._token.encode())

    def rotate(self) -> str:
        """Replace the token; the old one is refused from now on. Returns the new token."""
        with self._lock:
            old = self._token
            self._token = self._new()
            try:
                self._save()  # stored first: a failed save must leave the old token working
            except ConfigError:
                self._token = old
                raise
            self.generation += 1
        log.warning("pairing token rotated; phones must pair again with the new link")
        return self._token


class AllowList:
    """Source addresses allowed for protocols without a token: ``"192.168.1.0/24,10.0.0.7"``.

    Raises:
        ConfigError: an entry is not an address or network.
    """

    def __init__(self, spec: str | list[str] | None) -> None:
        items = spec.split(",") if isinstance(spec, str) else list(spec or [])
        self.networks: list[ipaddress.IPv4Network | ipaddress.IPv6Network] = []
        for item in (i.strip() for i in items):
            if not item:
                continue
            try:
                self.networks.append(ipaddress.ip_network(item, strict=False))
            except ValueError:
                raise ConfigError(f"allow-list entry {item!r} is not an address or network; expected e.g. "
                                  "192.168.1.23 or 192.168.1.0/24") from None

    def __bool__(self) -> bool:
        return bool(self.networks)

    def allows(self, host: str) -> bool:
        try:
            ip = ipaddress.ip_address(host.split("%", 1)[0])
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return any(ip in n for n in self.networks)

    def __str__(self) -> str:
        return ",".join(str(n) for n in self.networks) or "(nobody)"


class RateLimit:
    """A token bucket: ``rate`` messages per second, bursts up to ``burst``. Times are host ns."""

    __slots__ = ("_level", "_t", "burst", "rate")

    def __init__(self, rate: float, burst: float, t_ns: int) -> None:
        self.rate = rate
        self.burst = burst
        self._level = burst
        self._t = t_ns

    def allow(self, t_ns: int, cost: float = 1.0) -> bool:
        level = min(self.burst, self._level + (t_ns - self._t) * 1e-9 * self.rate)
        self._t = t_ns
        if level < cost:
            self._level = level
            return False
        self._level = level - cost
        return True


class RateBook:
    """Token buckets by key that outlive a connection: a client that closes and reconnects finds its
    bucket as it left it (empty, if it was flooding), so reconnecting buys it nothing.

    At most ``max_keys`` buckets are kept. Beyond that, buckets that have refilled to ``burst`` are
    forgotten first (a full bucket is the same as a new one: nothing is lost), then the least recently
    used ones (counted in ``evicted``: only a client spread over more than ``max_keys`` keys gets a
    fresh bucket that way, and the per-address bucket still holds it).
    """

    def __init__(self, rate: float, burst: float, max_keys: int = 4096) -> None:
        self.rate = rate
        self.burst = burst
        self.max_keys = max_keys
        self.evicted = 0
        self._b: dict[str, RateLimit] = {}

    def allow(self, key: str, t_ns: int, cost: float = 1.0) -> bool:
        b = self._b.pop(key, None)  # re-inserted last: the dict's order is the least recently used first
        if b is None:
            if len(self._b) >= self.max_keys:
                self._prune(t_ns)
            b = RateLimit(self.rate, self.burst, t_ns)
        self._b[key] = b
        return b.allow(t_ns, cost)

    def level(self, key: str, t_ns: int) -> float:
        """Tokens ``key`` has at ``t_ns`` (``burst`` for a key never seen or forgotten)."""
        b = self._b.get(key)
        if b is None:
            return self.burst
        return min(b.burst, b._level + max(0, t_ns - b._t) * 1e-9 * b.rate)

    def _prune(self, t_ns: int) -> None:
        full = [k for k in self._b if self.level(k, t_ns) >= self.burst]
        for k in full:
            del self._b[k]
        while len(self._b) >= self.max_keys:
            del self._b[next(iter(self._b))]
            self.evicted += 1

    def __len__(self) -> int:
        return len(self._b)


class Rejections:
    """Refused input, counted by reason; logged at the first of each reason and every 1000th."""

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()

    def count(self, reason: str, peer: str | None, detail: str = "") -> None:
        with self._lock:
            self.counts[reason] += 1
            n = self.counts[reason]
        if n == 1 or n % 1000 == 0:
            log.warning("refused %s from %s%s (%d so far; all are counted)", reason, peer or "?",
                        f": {detail}" if detail else "", n)
        else:
            log.debug("refused %s from %s %s", reason, peer, detail)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def as_dict(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counts)
