"""Authentication of the cloud server's clients: the CURVE allowlist (replaceable at any time, SIGHUP) with
refused handshakes logged, rate limited, and the allowlist names of client keys."""
import logging
import pathlib
import threading
import time
from typing import Dict, Optional

import zmq
import zmq.auth
import zmq.auth.thread
from zmq.utils import z85

from offload_cloud.keys import load_allowlist, load_server_keys, read_key_file

LOG = logging.getLogger("offload_cloud.server")


class RateLimitedLog:
    """Logs a line at most once per `period_s` for each key, then says how many were suppressed: a flood
    of BUSY replies or refused handshakes must not flood the log."""

    def __init__(self, logger: logging.Logger, period_s: float = 5.0):
        self.logger = logger
        self.period_s = period_s
        self._last = {}          # key -> (time logged, suppressed since)
        self._lock = threading.Lock()

    def log(self, level: int, key, message: str, *args) -> None:
        now = time.monotonic()
        with self._lock:
            logged_at, suppressed = self._last.get(key, (None, 0))
            if logged_at is not None and now - logged_at < self.period_s:
                self._last[key] = (logged_at, suppressed + 1)
                return
            self._last[key] = (now, 0)
            if len(self._last) > 1024:   # keys are few in practice; never let them grow without bound
                self._last.clear()
        if suppressed:
            message += f" ({suppressed} similar lines suppressed in the last {self.period_s:g} s)"
        self.logger.log(level, message, *args)


class Authenticator(zmq.auth.thread.ThreadAuthenticator):
    """ZAP handler with an allowlist the server can replace at any time (SIGHUP), logging refused
    handshakes at WARNING with the peer address, rate limited."""

    def __init__(self, context: zmq.Context, allowlist, refusals: RateLimitedLog):
        super().__init__(context, log=LOG)
        self.allowlist = allowlist     # frozenset of Z85 public keys; replaced whole, never mutated
        self.names: Dict[bytes, str] = {}   # Z85 public key -> allowlist name (the key file's stem)
        self.allowlist_dir = None
        self._refusals = refusals
        self._address = "?"

    def reload(self) -> bool:
        """Re-read the allowlist directory (SIGHUP); on an error keep the previous keys and say so."""
        allowlist_dir = self.allowlist_dir
        try:
            allowlist, names = load_allowlist(allowlist_dir), key_names(allowlist_dir)
        except (OSError, ValueError) as error:
            LOG.error("allowlist NOT reloaded, keeping the previous %d keys: %s", len(self.allowlist), error)
            return False
        old, self.allowlist, self.names = self.allowlist, allowlist, names
        LOG.warning("allowlist reloaded from %s: %d keys (%d admitted, %d revoked)", allowlist_dir, len(allowlist),
                    len(allowlist - old), len(old - allowlist))
        return True

    async def handle_zap_message(self, msg):
        self._address = msg[3].decode("utf-8", "replace") if len(msg) > 3 else "?"
        await super().handle_zap_message(msg)

    async def _authenticate_curve(self, domain, client_key):
        key = z85.encode(client_key)
        if key in self.allowlist:
            return True, b"OK"
        self._refusals.log(logging.WARNING, ("refused", self._address),
                           "refused a CURVE handshake from %s: client key %s is not on the allowlist",
                           self._address, key.decode())
        return False, b"Unknown key"


def key_names(clients_dir) -> Dict[bytes, str]:
    """Z85 public key -> allowlist name (the key file's stem, e.g. robot1) of every `*.key` in `clients_dir`."""
    return {read_key_file(path, need_secret=False)[0]: path.stem for path in sorted(pathlib.Path(clients_dir).glob("*.key"))}


def user_of(frame) -> Optional[bytes]:
    """The CURVE client key (Z85) libzmq attached to a message after its handshake."""
    try:
        user = frame.get("User-Id")
    except (zmq.ZMQError, AttributeError):
        return None
    return user.encode() if isinstance(user, str) else user


def curve_server(context: zmq.Context, frontend: zmq.Socket, keys_dir, refusals: RateLimitedLog) -> Authenticator:
    """CURVE on `frontend` with the server keys in `keys_dir` and the allowlist beside them; the running
    authenticator (its allowlist replaceable on SIGHUP)."""
    public, secret, allowlist_dir = load_server_keys(keys_dir)
    auth = Authenticator(context, load_allowlist(allowlist_dir), refusals)
    auth.names, auth.allowlist_dir = key_names(allowlist_dir), allowlist_dir
    auth.start()
    frontend.curve_secretkey, frontend.curve_publickey, frontend.curve_server = secret, public, True
    LOG.info("CURVE on; client allowlist %s (%d keys; SIGHUP reloads it)", allowlist_dir, len(auth.allowlist))
    return auth
