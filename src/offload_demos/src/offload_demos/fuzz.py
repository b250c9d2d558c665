"""Coverage-guided fuzzing (atheris, libFuzzer) of what reads hostile input: the wire protocol's decoders
and the map loaders (a STATS reply included). A target passes when every input either decodes or raises the module's own error
(ProtocolError, MapFormatError); anything else is a crash, and libFuzzer writes the input that caused it.

    python -m offload_demos.fuzz protocol -runs=50000
    python -m offload_demos.fuzz movingai -max_total_time=60

Targets: protocol, movingai, map_yaml, map_image. Extra arguments go to libFuzzer. A demo and test tool.
"""
import os
import sys
import tempfile

import atheris

with atheris.instrument_imports():
    from offload_cloud import protocol
    from offload_planner_cpp import maps

MAX_CELLS = 1 << 16
# A valid 4 x 3 map_server pair, so the YAML and the image are fuzzed one at a time.
PGM = b"P5\n4 3\n255\n" + bytes([254, 0, 205, 254] * 3)
YAML = b"image: map.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\noccupied_thresh: 0.65\n" \
       b"free_thresh: 0.196\n"


def frames_of(data: bytes):
    provider = atheris.FuzzedDataProvider(data)
    count = provider.ConsumeIntInRange(0, 5)
    frames = [provider.ConsumeBytes(provider.ConsumeIntInRange(0, 64)) for _ in range(count - 1)]
    return frames + [provider.ConsumeBytes(provider.remaining_bytes())] if count else frames


def protocol_target(data: bytes) -> None:
    frames = frames_of(data)
    # A real envelope half the time, so the fuzzer gets past the magic and version into the bodies.
    if frames and len(data) % 2:
        frames[0] = protocol.envelope(protocol.Kind(1 + len(data) % 4), len(data))
    for decode in (lambda: protocol.decode_envelope(frames[0] if frames else b""),
                   lambda: protocol.decode_stats(protocol.decode_reply(frames)),
                   lambda: protocol.decode_plan(7, frames[1:], MAX_CELLS),
                   lambda: protocol.decode_reply(frames),
                   lambda: protocol.decode_map(frames[0] if frames else b"", frames[-1] if frames else b"",
                                               MAX_CELLS)):
        try:
            decode()
        except protocol.ProtocolError:
            pass


def loader_target(write):
    # One per process, rewritten at every input, in the working directory (libFuzzer ends the process without
    # Python's clean-up, so a directory in /tmp would stay behind after every run).
    directory = tempfile.mkdtemp(prefix="offload-fuzz-", dir=os.getcwd())

    def target(data: bytes) -> None:
        path = write(directory, data)
        try:
            maps.load_map(path)
        except maps.MapFormatError:
            pass
    return target


def _movingai(directory, data):
    path = os.path.join(directory, "fuzz.map")
    with open(path, "wb") as out:
        out.write(data)
    return path


def _map_server(yaml_bytes, image_bytes):
    def write(directory, data):
        with open(os.path.join(directory, "map.pgm"), "wb") as out:
            out.write(image_bytes if image_bytes is not None else data)
        path = os.path.join(directory, "map.yaml")
        with open(path, "wb") as out:
            out.write(yaml_bytes if yaml_bytes is not None else data)
        return path
    return write


# Built only for the target fuzzed: a loader target makes its scratch directory.
TARGETS = {
    "protocol": lambda: protocol_target,
    "movingai": lambda: loader_target(_movingai),
    "map_yaml": lambda: loader_target(_map_server(None, PGM)),
    "map_image": lambda: loader_target(_map_server(YAML, None)),
}


def main(argv=None) -> None:
    argv = list(sys.argv if argv is None else argv)
    if len(argv) < 2 or argv[1] not in TARGETS:
        print(f"usage: {argv[0]} {{{','.join(TARGETS)}}} [libFuzzer options]", file=sys.stderr)
        sys.exit(2)
    target = TARGETS[argv[1]]()
    atheris.Setup([argv[0]] + argv[2:], target)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
