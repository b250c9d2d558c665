"""User-space WAN emulator: a TCP proxy between the bridge and the cloud server (this machine has no
`tc netem`). It delays every chunk by half the round trip plus jitter, caps the bandwidth per direction,
simulates lost segments as a retransmission delay, and stalls or resets the link during outages, from
flags or a trace file of round trips over time. For the demo and tests only; a deployment has a real WAN.

    python -m offload_demos.wan_emulator --listen tcp://127.0.0.1:6000 \\
        --upstream tcp://127.0.0.1:5555 --rtt-ms 40 --jitter-ms 5 --bandwidth-mbps 20 --outage 30:5

Trace file: one `time_s rtt_ms` pair per line (comma or space separated, # comments), the round trip
holding from that time on; with --loop-trace the trace repeats.
"""
import argparse
import asyncio
import bisect
import logging
import math
import random
import signal
import sys
import threading
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

from offload_cloud.cli_args import bounded_float

LOG = logging.getLogger("offload_demos.wan_emulator")
_CHUNK_BYTES = 65536
_QUEUED_CHUNKS = 1024      # per direction: at most 64 MiB held during a stall


@dataclass
class LinkModel:
    """The emulated link. Times are seconds since the emulator started; the trace and the outages run from
    schedule_origin_s on that clock (a run's shared epoch), before which the trace's first sample holds."""
    rtt_s: float = 0.0
    jitter_s: float = 0.0                 # one-way delay varies uniformly by +- jitter_s / 2
    bandwidth_bps: float = 0.0            # per direction; 0 is unlimited
    loss: float = 0.0                     # probability a chunk waits for a retransmission
    retransmission_s: float = 0.2         # Linux's minimum TCP RTO
    outages: List[Tuple[float, float]] = field(default_factory=list)   # (start_s, duration_s)
    trace: List[Tuple[float, float]] = field(default_factory=list)     # (time_s, rtt_s), sorted
    loop_trace: bool = False
    reset_on_outage: bool = False         # close connections at an outage instead of stalling them
    seed: Optional[int] = None
    schedule_origin_s: float = 0.0

    def __post_init__(self):
        for name in ("rtt_s", "jitter_s", "bandwidth_bps", "retransmission_s"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if not 0.0 <= self.loss <= 1.0:   # also refuses NaN
            raise ValueError(f"loss must be a share in 0..1, got {self.loss!r}")
        for start, duration in self.outages:
            if not (math.isfinite(start) and math.isfinite(duration) and start >= 0 and duration > 0):
                raise ValueError(f"an outage needs a finite start >= 0 s and duration > 0 s, got {start!r}:{duration!r}")
        for time_s, rtt_s in self.trace:
            if not (math.isfinite(time_s) and math.isfinite(rtt_s) and time_s >= 0 and rtt_s >= 0):
                raise ValueError(f"a trace sample needs finite time and round trip >= 0, got {time_s!r} {rtt_s!r}")
        self.trace = sorted(self.trace)
        self._trace_times = [t for t, _ in self.trace]
        self._random = random.Random(self.seed)

    def round_trip_s(self, t: float) -> float:
        """The base round trip at time t: from the trace when there is one, else rtt_s."""
        if not self.trace:
            return self.rtt_s
        t = max(t - self.schedule_origin_s, 0.0)
        if self.loop_trace and self._trace_times[-1] > 0:
            t = t % self._trace_times[-1]
        k = bisect.bisect_right(self._trace_times, t) - 1
        return self.trace[max(k, 0)][1]

    def one_way_s(self, t: float) -> float:
        delay = self.round_trip_s(t) / 2 + self._random.uniform(-self.jitter_s / 2, self.jitter_s / 2)
        if self.loss and self._random.random() < self.loss:
            delay += self.retransmission_s
        return max(0.0, delay)

    def outage_end(self, t: float) -> Optional[float]:
        """End of the outage containing t, or None."""
        t -= self.schedule_origin_s
        for start, duration in self.outages:
            if start <= t < start + duration:
                return self.schedule_origin_s + start + duration
        return None


class _Direction:
    """Release schedule of one direction: chunks leave in order, no faster than the bandwidth."""

    def __init__(self, link: LinkModel):
        self.link = link
        self.wire_free_at = 0.0
        self.last_release = 0.0

    def release_time(self, now: float, size: int) -> float:
        start = max(now, self.wire_free_at)
        if self.link.bandwidth_bps > 0:
            self.wire_free_at = start + size * 8 / self.link.bandwidth_bps
        else:
            self.wire_free_at = start
        self.last_release = max(self.wire_free_at + self.link.one_way_s(now), self.last_release)
        return self.last_release


def parse_endpoint(endpoint: str) -> Tuple[str, int]:
    host, _, port = endpoint.replace("tcp://", "").rpartition(":")
    if not host or not port.isdigit() or int(port) > 65535:
        raise ValueError(f"endpoint must be tcp://HOST:PORT with a port in 0..65535, got {endpoint!r}")
    return host, int(port)


def read_trace(path: str) -> List[Tuple[float, float]]:
    """(time_s, rtt_s) pairs of a trace file of `time_s rtt_ms` lines."""
    trace = []
    with open(path) as lines:
        for number, line in enumerate(lines, 1):
            line = line.split("#", 1)[0].replace(",", " ").split()
            if not line:
                continue
            try:
                time_s, rtt_ms = float(line[0]), float(line[1])
            except (ValueError, IndexError):
                raise ValueError(f"{path}:{number}: expected `time_s rtt_ms`") from None
            trace.append((time_s, rtt_ms / 1e3))
    if not trace:
        raise ValueError(f"{path}: no samples")
    return trace


class WanEmulator:
    """The proxy. run() serves in the calling thread until stop(); start() runs it in a thread."""

    def __init__(self, listen: str, upstream: str, link: LinkModel, epoch: Optional[float] = None):
        """`epoch`: the time.monotonic() second at which the link's trace and outages start, shared with the
        run's other schedules; None: when the emulator starts."""
        if epoch is not None and not math.isfinite(epoch):
            raise ValueError(f"epoch must be a finite time.monotonic() value, got {epoch!r}")
        self.epoch = epoch
        self.listen_host, self.listen_port = parse_endpoint(listen)
        self.upstream = parse_endpoint(upstream)
        self.link = link
        self._loop = None
        self._stopped = None
        self._thread = None
        self._ready = threading.Event()
        self._failure: Optional[BaseException] = None   # why run() could not serve (e.g. port taken)
        self._writers = set()
        # TCP payload bytes forwarded client->server and server->client (the benchmark's bytes on the wire).
        self.bytes_up = 0
        self.bytes_down = 0

    @property
    def endpoint(self) -> str:
        return f"tcp://{self.listen_host}:{self.listen_port}"

    def start(self) -> str:
        self._thread = threading.Thread(target=self.run, name="wan-emulator", daemon=True)
        self._thread.start()
        if not self._ready.wait(10.0):
            raise RuntimeError("WAN emulator did not start")
        if self._failure is not None:
            raise self._failure
        return self.endpoint

    def stop(self) -> None:
        if self._loop is not None and self._stopped is not None:
            self._loop.call_soon_threadsafe(self._stopped.set)
        if self._thread is not None and threading.current_thread() is not self._thread:
            self._thread.join(10.0)

    def run(self) -> None:
        try:
            asyncio.run(self._serve())
        except OSError as error:   # the listen port is taken or not ours: start() reports it at once
            self._failure = OSError(error.errno, f"cannot listen on {self.endpoint}: {error.strerror}")
            self._ready.set()

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stopped = asyncio.Event()
        self._started_at = self._loop.time()   # the event loop's clock is time.monotonic()
        if self.epoch is not None:
            self.link.schedule_origin_s = self.epoch - self._started_at
        server = await asyncio.start_server(self._on_client, self.listen_host, self.listen_port)
        self.listen_port = server.sockets[0].getsockname()[1]
        watcher = asyncio.create_task(self._reset_at_outages()) if self.link.reset_on_outage else None
        LOG.info("emulating a WAN on %s -> %s:%d", self.endpoint, *self.upstream)
        self._ready.set()
        async with server:
            await self._stopped.wait()
        if watcher:
            watcher.cancel()
        for writer in list(self._writers):
            writer.close()

    def _now(self) -> float:
        return self._loop.time() - self._started_at

    async def _reset_at_outages(self) -> None:
        for start, _ in sorted(self.link.outages):
            await asyncio.sleep(max(0.0, self.link.schedule_origin_s + start - self._now()))
            LOG.info("outage: resetting %d connections", len(self._writers))
            for writer in list(self._writers):
                writer.transport.abort()

    async def _on_client(self, client_reader, client_writer) -> None:
        if self.link.reset_on_outage and self.link.outage_end(self._now()) is not None:
            client_writer.transport.abort()   # refused: the link is down
            return
        try:
            upstream_reader, upstream_writer = await asyncio.open_connection(*self.upstream)
        except OSError as error:
            LOG.warning("upstream %s:%d unreachable: %s", *self.upstream, error)
            client_writer.transport.abort()
            return
        self._writers.update((client_writer, upstream_writer))
        try:
            await asyncio.gather(self._pump(client_reader, upstream_writer, "bytes_up"),
                                 self._pump(upstream_reader, client_writer, "bytes_down"))
        finally:
            for writer in (client_writer, upstream_writer):
                self._writers.discard(writer)
                writer.close()

    async def _pump(self, reader, writer, counter: str) -> None:
        direction = _Direction(self.link)
        queue = asyncio.Queue(_QUEUED_CHUNKS)

        async def receive():
            try:
                while True:
                    data = await reader.read(_CHUNK_BYTES)
                    if not data:
                        break
                    await queue.put((direction.release_time(self._now(), len(data)), data))
            except (ConnectionError, OSError):
                pass
            await queue.put(None)

        async def deliver():
            while True:
                item = await queue.get()
                if item is None:
                    break
                release, data = item
                while True:
                    wait_s = release - self._now()
                    end = self.link.outage_end(max(release, self._now()))
                    if end is not None:   # stalled: nothing moves until the outage ends
                        release = max(release, end)
                        continue
                    if wait_s <= 0:
                        break
                    await asyncio.sleep(wait_s)
                writer.write(data)
                setattr(self, counter, getattr(self, counter) + len(data))
                await writer.drain()
            if writer.can_write_eof():
                writer.write_eof()

        receiver = asyncio.create_task(receive())
        try:
            await deliver()
        except (ConnectionError, OSError):
            pass
        finally:
            receiver.cancel()
            writer.close()


def parse_outage(text: str) -> Tuple[float, float]:
    start, _, duration = text.partition(":")
    try:
        start_s, duration_s = float(start), float(duration)
    except ValueError:
        raise argparse.ArgumentTypeError(f"outage must be START_S:DURATION_S, got {text!r}") from None
    if not (math.isfinite(start_s) and math.isfinite(duration_s) and start_s >= 0 and duration_s > 0):
        raise argparse.ArgumentTypeError(f"outage needs a finite START_S >= 0 and DURATION_S > 0, got {text!r}")
    return start_s, duration_s


def main(argv: Sequence[str] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--listen", default="tcp://127.0.0.1:6000", help="where the bridge connects")
    parser.add_argument("--upstream", required=True, help="the cloud server's endpoint")
    parser.add_argument("--rtt-ms", type=bounded_float("--rtt-ms", 0.0, 1e9), default=0.0, help="base round trip added (ms)")
    parser.add_argument("--jitter-ms", type=bounded_float("--jitter-ms", 0.0, 1e9), default=0.0, help="one-way delay spread, uniform (ms)")
    parser.add_argument("--bandwidth-mbps", type=bounded_float("--bandwidth-mbps", 0.0, 1e9), default=0.0, help="per direction, 0 unlimited (Mbit/s)")
    parser.add_argument("--loss", type=bounded_float("--loss", 0.0, 1.0), default=0.0, help="share of chunks delayed by a 200 ms retransmission")
    parser.add_argument("--outage", type=parse_outage, action="append", default=[], metavar="START_S:DURATION_S",
                        help="stall the link for DURATION_S from START_S (repeatable)")
    parser.add_argument("--reset-on-outage", action="store_true", help="drop connections during outages instead")
    parser.add_argument("--trace", help="file of `time_s rtt_ms` lines; overrides --rtt-ms")
    parser.add_argument("--loop-trace", action="store_true", help="repeat the trace")
    parser.add_argument("--seed", type=int, help="seed of the jitter and loss draws")
    parser.add_argument("--epoch", type=bounded_float("--epoch", 0.0), default=0.0,
                        help="CLOCK_MONOTONIC second at which the trace and the outages start, shared with a run's "
                             "other schedules; 0: when the emulator starts")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    try:
        link = LinkModel(rtt_s=args.rtt_ms / 1e3, jitter_s=args.jitter_ms / 1e3,
                         bandwidth_bps=args.bandwidth_mbps * 1e6, loss=args.loss, outages=args.outage,
                         trace=read_trace(args.trace) if args.trace else [], loop_trace=args.loop_trace,
                         reset_on_outage=args.reset_on_outage, seed=args.seed)
        emulator = WanEmulator(args.listen, args.upstream, link, args.epoch or None)
        emulator.start()
    except (OSError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"listening on {emulator.endpoint}", flush=True)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    while not stop.wait(0.5):
        pass
    emulator.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
