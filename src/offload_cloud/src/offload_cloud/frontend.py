"""The server's robot-facing ROUTER socket: the bounds libzmq enforces on it, TCP keepalive, its bind and its
monitor."""
import logging
from typing import Optional, Tuple

import zmq

from offload_cloud import curve_speed, map_frames
from offload_cloud.auth import Authenticator, RateLimitedLog, curve_server
from offload_cloud.server_config import ServerConfig


def robot_socket(context: zmq.Context, config: ServerConfig) -> zmq.Socket:
    """A ROUTER with the message size, high-water mark and keepalive of `config`, not yet bound."""
    frontend = context.socket(zmq.ROUTER)
    frontend.linger = 0
    # libzmq bounds each frame, not a message: the broker refuses a message over the max size (TOO_LARGE). A frame
    # over the bound makes libzmq drop the connection: an I/O thread decrypts a frame whole (map_frames.py).
    frontend.setsockopt(zmq.MAXMSGSIZE, config.max_frame_bytes + map_frames.FRAME_SLACK_BYTES)
    # Incoming messages wait in libzmq until read (per connection); a small high-water mark bounds that
    # memory: at most the queued bytes budget's worth of maximum-size messages, and 2 x max_queued.
    frontend.rcvhwm = config.receive_hwm
    frontend.router_mandatory = False
    # A connection that never completes its handshake (a greeting, then nothing) holds a descriptor and, behind
    # HAProxy, a slot there: closed after this (libzmq's own default is 30 s).
    frontend.setsockopt(zmq.HANDSHAKE_IVL, int(config.handshake_timeout_s * 1000))
    if config.keepalive_s:
        # A peer gone without a FIN (power loss, a NAT that forgot the connection) is dropped, so it neither
        # holds memory nor counts against its key's connections. The kernel's keepalive, not ZMTP heartbeats:
        # those wait for a whole message, so they would drop a robot whose large upload takes longer.
        frontend.setsockopt(zmq.TCP_KEEPALIVE, 1)
        frontend.setsockopt(zmq.TCP_KEEPALIVE_IDLE, max(1, round(config.keepalive_s)))
        frontend.setsockopt(zmq.TCP_KEEPALIVE_INTVL, 10)
        frontend.setsockopt(zmq.TCP_KEEPALIVE_CNT, 3)
    return frontend


def open_frontend(context: zmq.Context, config: ServerConfig, log_limited: RateLimitedLog,
                  log: logging.Logger) -> Tuple[zmq.Socket, Optional[Authenticator], str]:
    """The bound frontend, its CURVE allowlist (None with --insecure) and the endpoint bound."""
    frontend = robot_socket(context, config)
    auth = None
    try:
        if config.insecure:
            log.warning("running INSECURE: plaintext and no client authentication (--insecure)")
        else:
            auth = curve_server(context, frontend, config.keys_dir, log_limited)
            if curve_speed.bundled_libsodium():
                log.warning("CURVE runs through the libsodium bundled in pyzmq's wheel, about 25x slower than the "
                            "system's: a large map holds an I/O thread for seconds. Fix: %s", curve_speed.REMEDY)
        endpoint = bind(frontend, config.bind)
    except BaseException:
        if auth is not None:
            auth.stop()
        frontend.close(0)
        raise
    return frontend, auth, endpoint


def monitor_socket(context: zmq.Context, frontend: zmq.Socket, events: int) -> zmq.Socket:
    """The frontend's connection events on a PAIR without a high-water mark: libzmq drops an event when the
    monitor's pipe is full (1000 by default), and a flood of connections would make the guard lose accepts
    and closes."""
    address = f"inproc://monitor-{id(frontend)}"
    frontend.monitor(address, events)
    monitor = context.socket(zmq.PAIR)
    monitor.rcvhwm = 0   # the inproc pipe's bound is the sum of both ends' marks, and 0 means none
    monitor.linger = 0
    monitor.connect(address)
    return monitor


def bind(frontend: zmq.Socket, endpoint: str) -> str:
    """Binds `endpoint` (port 0: a random free port) and returns the endpoint bound."""
    if endpoint.endswith(":0"):
        host = endpoint.rsplit(":", 1)[0]
        return f"{host}:{frontend.bind_to_random_port(host)}"
    frontend.bind(endpoint)
    return frontend.last_endpoint.decode()
