"""The cloud server's command line: `offload-cloud-server` (or `python -m offload_cloud`)."""
import argparse
import logging
import signal
import sys

import zmq

from offload_cloud.cli_args import bounded_float, bounded_int
from offload_cloud.metrics import parse_bind
from offload_cloud.server import LOG, CloudServer, ServerConfig
from offload_cloud.gc_pauses import freeze_startup_heap


def _endpoint(text: str) -> str:
    """tcp://HOST:PORT with PORT 0..65535 (0: a free one), or ipc:// / inproc://."""
    if text.startswith(("ipc://", "inproc://")):
        return text
    host, _, port = text[len("tcp://"):].rpartition(":") if text.startswith("tcp://") else ("", "", "")
    if not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"endpoint must be tcp://HOST:PORT with a port in 0..65535, got {text!r}")
    return text


def metrics_bind(text: str) -> str:
    """HOST:PORT for the Prometheus endpoint (metrics.parse_bind)."""
    try:
        parse_bind(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description="Cloud path planner (ROS-free).")
    parser.add_argument("--bind", type=_endpoint, default="tcp://0.0.0.0:5555",
                        help="ZeroMQ endpoint to listen on; port 0 picks a free one (default tcp://0.0.0.0:5555)")
    parser.add_argument("--workers", type=bounded_int("--workers", 1, 256), default=2, help="planner threads (default 2)")
    parser.add_argument("--io-threads", type=bounded_int("--io-threads", 1, 64), default=2,
                        help="libzmq I/O threads, where CURVE is decrypted a frame at a time (default 2)")
    parser.add_argument("--keys-dir", help="server keys dir from offload_cloud.keys (server.key_secret, clients/)")
    parser.add_argument("--insecure", action="store_true", help="plaintext, no client allowlist (tests, trusted LAN)")
    parser.add_argument("--cache-mib", type=bounded_int("--cache-mib", 0, 1 << 20), default=1024,
                        help="map cache memory cap in MiB, cells plus 1 KiB per map (default 1024)")
    parser.add_argument("--max-message-mib", type=bounded_int("--max-message-mib", 1, 4096), default=64, help="largest accepted message in MiB (default 64)")
    parser.add_argument("--max-queued", type=bounded_int("--max-queued", 1, 1 << 20), default=64, help="requests waiting for a worker before BUSY (64)")
    parser.add_argument("--max-queued-mib", type=bounded_int("--max-queued-mib", 1, 1 << 20), default=256,
                        help="bytes of the requests waiting for a worker, in MiB, before BUSY (default 256)")
    parser.add_argument("--max-pending-mib", type=bounded_int("--max-pending-mib", 1, 1 << 20), default=1024,
                        help="bytes all connections together may hold in messages still being received, in MiB; "
                             "over it the connections holding the most are cut (default 1024)")
    parser.add_argument("--max-pending-per-key-mib", type=bounded_int("--max-pending-per-key-mib", 1, 1 << 20),
                        default=384, help="the same for the connections of one client key (default 384)")
    parser.add_argument("--max-connections-per-key", type=bounded_int("--max-connections-per-key", 0, 65536),
                        default=32, help="open connections one client key may have; beyond it the key's least "
                                         "recently active one is cut (default 32; 0: no bound)")
    parser.add_argument("--max-connections", type=bounded_int("--max-connections", 0, 1 << 20), default=0,
                        help="open TCP connections in all; over it the oldest that has not said whose it is (else the "
                             "least recently active) is cut (default 0: the descriptor limit, raised to its hard "
                             "limit at start, less the server's own and a margin of 1/16)")
    parser.add_argument("--max-first-message-mib", type=bounded_int("--max-first-message-mib", 1, 4096), default=1,
                        help="largest first message of a connection, in MiB; clients of this release ping ahead of a "
                             "larger one. Raise it to --max-message-mib while robots from before the rule remain "
                             "(default 1)")
    parser.add_argument("--max-frame-mib", type=bounded_int("--max-frame-mib", 1, 4096), default=1,
                        help="largest frame in MiB; a larger one makes libzmq drop the connection (an I/O thread "
                             "decrypts a frame whole, serving no other connection meanwhile). Clients of this release "
                             "send a map in frames of 1 MiB; raise it to --max-message-mib while robots from before "
                             "the rule remain (default 1)")
    parser.add_argument("--max-pending-unidentified-mib",
                        type=bounded_int("--max-pending-unidentified-mib", 1, 1 << 20), default=64,
                        help="bytes the connections yet to send their first message may hold together, in MiB; over "
                             "it the oldest are cut (default 64)")
    parser.add_argument("--keepalive-s", type=bounded_float("--keepalive-s", 0, 86400), default=30.0,
                        help="TCP keepalive: seconds a connection is idle before the kernel probes its peer (3 probes "
                             "10 s apart); a peer gone without a FIN is dropped (default 30; 0: none)")
    parser.add_argument("--handshake-timeout-s", type=bounded_float("--handshake-timeout-s", 0, 3600), default=10.0,
                        help="a connection that has not completed its ZMTP/CURVE handshake by then is closed (default "
                             "10; 0: none)")
    parser.add_argument("--max-wait-s", type=bounded_float("--max-wait-s", 0, 3600, low_open=True), default=1.0,
                        help="longest a request waits for a worker before it gets BUSY instead (default 1.0); "
                             "keep it under the robots' per-attempt timeout")
    parser.add_argument("--rate-per-client", type=bounded_float("--rate-per-client", 0, 1e6), default=50.0,
                        help="plans (and uploads) per second one client (CURVE key; connection if --insecure) may "
                             "have while the server is busy; over it BUSY (default 50; 0: no limit)")
    parser.add_argument("--burst-per-client", type=bounded_int("--burst-per-client", 1, 1000000), default=100,
                        help="token bucket size of --rate-per-client (default 100)")
    parser.add_argument("--stats-admin", action="append", default=[], metavar="KEY_NAME",
                        help="a client key name whose STATS show every client (repeatable); the others see "
                             "their own figures only")
    parser.add_argument("--stats-log-s", type=bounded_float("--stats-log-s", 0, 86400), default=60.0,
                        help="log a line of the STATS counters every this many seconds (default 60; 0: never)")
    parser.add_argument("--metrics-bind", type=metrics_bind, metavar="HOST:PORT",
                        help="serve Prometheus metrics (the STATS counters) at http://HOST:PORT/metrics; port 0 picks "
                             "a free one. Unauthenticated: bind a private address (default: off)")
    parser.add_argument("--log-level", default="INFO", type=str.upper, choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                        help="DEBUG, INFO, WARNING or ERROR (default INFO)")
    args = parser.parse_args(argv)
    if args.max_first_message_mib > args.max_message_mib:
        parser.error(f"--max-first-message-mib ({args.max_first_message_mib}) must be <= --max-message-mib "
                     f"({args.max_message_mib})")
    if args.max_frame_mib > args.max_message_mib:
        parser.error(f"--max-frame-mib ({args.max_frame_mib}) must be <= --max-message-mib ({args.max_message_mib})")
    if args.max_pending_unidentified_mib < args.max_first_message_mib:
        parser.error(f"--max-pending-unidentified-mib ({args.max_pending_unidentified_mib}) must be >= "
                     f"--max-first-message-mib ({args.max_first_message_mib})")
    for name in ("max_queued_mib", "max_pending_mib", "max_pending_per_key_mib"):
        if getattr(args, name) < args.max_message_mib:
            parser.error(f"--{name.replace('_', '-')} ({getattr(args, name)}) must be >= --max-message-mib "
                         f"({args.max_message_mib})")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(threadName)s: %(message)s")
    if not args.insecure and not args.keys_dir:
        LOG.error("--keys-dir is required (CURVE is on by default); pass --insecure for plaintext")
        return 2
    try:
        server = CloudServer(ServerConfig(
            bind=args.bind, workers=args.workers, io_threads=args.io_threads, keys_dir=args.keys_dir,
            insecure=args.insecure,
            cache_bytes=args.cache_mib << 20, max_message_bytes=args.max_message_mib << 20,
            max_frame_bytes=args.max_frame_mib << 20,
            max_queued=args.max_queued, max_queued_bytes=args.max_queued_mib << 20,
            max_pending_bytes=args.max_pending_mib << 20, max_pending_bytes_per_key=args.max_pending_per_key_mib << 20,
            max_connections_per_key=args.max_connections_per_key, max_connections=args.max_connections,
            max_first_message_bytes=args.max_first_message_mib << 20,
            max_pending_unidentified_bytes=args.max_pending_unidentified_mib << 20, keepalive_s=args.keepalive_s,
            handshake_timeout_s=args.handshake_timeout_s,
            max_wait_s=args.max_wait_s, rate_per_client=args.rate_per_client, burst_per_client=args.burst_per_client,
            stats_log_s=args.stats_log_s, stats_admins=tuple(args.stats_admin), metrics_bind=args.metrics_bind))
    except (OSError, ValueError, zmq.ZMQError) as error:
        LOG.error("cannot start: %s", error)
        return 2
    except Exception as error:   # never a traceback for bad keys or settings: one line naming the cause
        LOG.error("cannot start: %s: %s", type(error).__name__, error)
        return 2
    # The handlers only set the stop flag; the broker notices within one poll period and exits cleanly.
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: server.stop())
    signal.signal(signal.SIGHUP, lambda *_: server.reload_allowlist())   # as sshd and nginx: re-read keys
    print(f"listening on {server.endpoint}", flush=True)
    if server.metrics is not None:
        print(f"metrics on http://{server.metrics.address}/metrics", flush=True)
    freeze_startup_heap()
    server.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
