"""The cloud server's settings, checked once at construction."""
from dataclasses import dataclass
from typing import Optional

from offload_cloud.map_frames import FRAME_MAX_BYTES
from offload_cloud.metrics import parse_bind
from offload_cloud.protocol import FIRST_MESSAGE_MAX_BYTES


@dataclass
class ServerConfig:
    bind: str = "tcp://127.0.0.1:5555"
    workers: int = 2
    io_threads: int = 2                   # libzmq I/O threads: CURVE is decrypted there, a frame at a time
    keys_dir: Optional[str] = None        # CURVE keys and client allowlist; required unless insecure
    insecure: bool = False                # plaintext, no client authentication
    cache_bytes: int = 1 << 30            # map cache memory cap (cells + ENTRY_OVERHEAD_BYTES per map)
    max_message_bytes: int = 64 << 20     # larger messages are refused (TOO_LARGE)
    max_frame_bytes: int = FRAME_MAX_BYTES   # a larger frame makes libzmq drop the connection: an I/O thread decrypts
                                          # a frame whole, serving no other connection meanwhile (map_frames.py); up
                                          # to max_message_bytes for robots from before clients split maps
    max_queued: int = 64                  # plan requests waiting for a worker; more get BUSY
    max_queued_bytes: int = 256 << 20     # and their bytes: a request that would exceed it gets BUSY
    max_pending_bytes: int = 1 << 30      # bytes all connections together may hold undelivered (messages
                                          # libzmq is still receiving); over it the largest holders are cut
    max_pending_bytes_per_key: int = 384 << 20   # the same for the connections of one client key
    max_connections_per_key: int = 32     # open connections of one client key; 0: no bound
    max_connections: int = 0              # open TCP connections in all; 0: what fits the descriptor limit
    max_first_message_bytes: int = FIRST_MESSAGE_MAX_BYTES   # largest first message of a connection; up to
                                          # max_message_bytes for robots from before the rule
    max_pending_unidentified_bytes: int = 64 << 20   # what connections yet to send a message hold together
    keepalive_s: float = 30.0             # TCP keepalive: idle seconds before the first probe (3 probes, 10 s
                                          # apart); a peer gone without a FIN is dropped; 0: none
    handshake_timeout_s: float = 10.0     # a connection that has not completed its ZMTP/CURVE handshake by then is
                                          # closed (libzmq's own default: 30 s); 0: none
    max_wait_s: float = 1.0               # longest a request may wait for a worker; then BUSY, not planned
    rate_per_client: float = 50.0         # plans (and uploads) per second a client may have while others
    burst_per_client: int = 100           # wait; and its bucket's size. rate 0: no rate limit
    stats_log_s: float = 60.0             # period of the stats log line; 0: none
    stats_admins: tuple = ()              # client key names whose STATS show every client; others see
                                          # their own figures only (a local, inproc/ipc, caller sees all)
    metrics_bind: Optional[str] = None    # HOST:PORT of the Prometheus endpoint (GET /metrics); None: off

    @property
    def receive_hwm(self) -> int:
        """Messages libzmq may hold unread per connection: the queued bytes budget's worth of maximum-size
        messages, at most 2 x max_queued, at least 2."""
        return max(2, min(2 * self.max_queued, self.max_queued_bytes // self.max_message_bytes))

    @property
    def max_frames(self) -> int:
        """Frames of the longest valid message (a plan carrying a map of max_message_bytes cells in the clients'
        frames); a message of more is dropped unread."""
        return 3 + -(-self.max_message_bytes // FRAME_MAX_BYTES)

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """Raises ValueError naming the first setting out of its range."""
        if not self.insecure and not self.keys_dir:
            raise ValueError("a keys dir is required unless --insecure is given")
        if self.workers < 1:
            raise ValueError("at least one worker is needed")
        if not 1 <= self.io_threads <= 64:
            raise ValueError(f"the I/O threads must be 1..64, got {self.io_threads}")
        if self.max_message_bytes < 1 or self.cache_bytes < 0:
            raise ValueError("the max message size must be >= 1 byte and the cache cap >= 0")
        if not (0 <= self.rate_per_client <= 1e6 and 1 <= self.burst_per_client <= 1e6):
            raise ValueError("the rate per client must be in 0..1e6 plans/s and the burst in 1..1e6")
        if not 0 <= self.stats_log_s <= 86400:
            raise ValueError(f"the stats log period must be in 0..86400 s, got {self.stats_log_s}")
        if not 0 < self.max_wait_s <= 3600:
            raise ValueError(f"the max wait must be in (0, 3600] s, got {self.max_wait_s}")
        if self.max_queued < 1 or self.max_queued_bytes < self.max_message_bytes:
            raise ValueError("max queued must be >= 1 and the queued bytes budget at least the max message size")
        if not FIRST_MESSAGE_MAX_BYTES <= self.max_first_message_bytes <= self.max_message_bytes:
            raise ValueError(f"the first message bound must be in {FIRST_MESSAGE_MAX_BYTES}..{self.max_message_bytes} "
                             f"bytes (the protocol's to the max message size), got {self.max_first_message_bytes}")
        if not FRAME_MAX_BYTES <= self.max_frame_bytes <= self.max_message_bytes:
            raise ValueError(f"the frame bound must be in {FRAME_MAX_BYTES}..{self.max_message_bytes} bytes (the "
                             f"clients' frame size to the max message size), got {self.max_frame_bytes}")
        if self.max_pending_unidentified_bytes < self.max_first_message_bytes:
            raise ValueError("the unidentified connections' budget must be at least the first message bound")
        if not 0 <= self.handshake_timeout_s <= 3600:
            raise ValueError(f"the handshake timeout must be in 0..3600 s, got {self.handshake_timeout_s}")
        if not 0 <= self.keepalive_s <= 86400:
            raise ValueError(f"the keepalive idle time must be in 0..86400 s, got {self.keepalive_s}")
        if not 0 <= self.max_connections <= 1 << 20:
            raise ValueError(f"the max connections must be in 0..{1 << 20}, got {self.max_connections}")
        if not 0 <= self.max_connections_per_key <= 65536:
            raise ValueError(f"the connections per key must be in 0..65536, got {self.max_connections_per_key}")
        if self.metrics_bind is not None:
            parse_bind(self.metrics_bind)
        if min(self.max_pending_bytes, self.max_pending_bytes_per_key) < self.max_message_bytes:
            raise ValueError("the pending bytes budgets (in all and per key) must be at least the max message size")
