"""The server's robot-facing ROUTER socket: the bounds libzmq enforces on it, TCP keepalive, and its bind."""
import zmq

from offload_cloud.server_config import ServerConfig


def robot_socket(context: zmq.Context, config: ServerConfig) -> zmq.Socket:
    """A ROUTER with the message size, high-water mark and keepalive of `config`, not yet bound."""
    frontend = context.socket(zmq.ROUTER)
    frontend.linger = 0
    frontend.setsockopt(zmq.MAXMSGSIZE, config.max_message_bytes)
    # Incoming messages wait in libzmq until read (per connection); a small high-water mark bounds that
    # memory: at most the queued bytes budget's worth of maximum-size messages, and 2 x max_queued.
    frontend.rcvhwm = config.receive_hwm
    frontend.router_mandatory = False
    if config.keepalive_s:
        # A peer gone without a FIN (power loss, a NAT that forgot the connection) is dropped, so it neither
        # holds memory nor counts against its key's connections. The kernel's keepalive, not ZMTP heartbeats:
        # those wait for a whole message, so they would drop a robot whose large upload takes longer.
        frontend.setsockopt(zmq.TCP_KEEPALIVE, 1)
        frontend.setsockopt(zmq.TCP_KEEPALIVE_IDLE, max(1, round(config.keepalive_s)))
        frontend.setsockopt(zmq.TCP_KEEPALIVE_INTVL, 10)
        frontend.setsockopt(zmq.TCP_KEEPALIVE_CNT, 3)
    return frontend


def bind(frontend: zmq.Socket, endpoint: str) -> str:
    """Binds `endpoint` (port 0: a random free port) and returns the endpoint bound."""
    if endpoint.endswith(":0"):
        host = endpoint.rsplit(":", 1)[0]
        return f"{host}:{frontend.bind_to_random_port(host)}"
    frontend.bind(endpoint)
    return frontend.last_endpoint.decode()
