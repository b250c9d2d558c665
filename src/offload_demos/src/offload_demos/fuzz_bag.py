"""Coverage-guided fuzzing (atheris, libFuzzer) of the bag reader: any file either reads or is refused
with BagReadError naming it, within libFuzzer's memory and time limits (a hang or a runaway allocation is
a crash too). The corpus starts from small real bags (indexed, lz4, bz2, cut off) written here.

    python -m offload_demos.fuzz_bag -runs=2000
    python -m offload_demos.fuzz_bag -max_total_time=120 -rss_limit_mb=1024

A test tool, not shipped to a robot.
"""
import os
import sys
import tempfile

import atheris

with atheris.instrument_imports():
    from offload_learner_py.data import bags
from offload_demos.bag_writer import probe_request, unindex, write_requests


def seed_corpus(directory: str) -> None:
    requests = [probe_request(100 + k, 0.1 * (k + 1), 0.5, 0.03, 0.02 * (k + 1), 0.05, k % 2, 0.5, 0.1 * k)
                for k in range(6)]
    for compression in ("none", "lz4", "bz2"):
        write_requests(os.path.join(directory, f"seed_{compression}.bag"), requests, compression=compression,
                       chunk_bytes=512)
    cut = os.path.join(directory, "seed_cut.bag")
    write_requests(cut, requests)
    unindex(cut, keep_bytes=os.path.getsize(cut) * 2 // 3)


def main(argv=None) -> None:
    argv = list(sys.argv if argv is None else argv)
    # In the working directory: libFuzzer ends the process without Python's clean-up.
    work = tempfile.mkdtemp(prefix="offload-fuzz-bag-", dir=os.getcwd())
    corpus = os.path.join(work, "corpus")
    os.mkdir(corpus)
    seed_corpus(corpus)
    path = os.path.join(work, "input.bag")

    def target(data: bytes) -> None:
        with open(path, "wb") as out:
            out.write(data)
        try:
            bags.read_bag(path)
        except bags.BagReadError:
            pass

    atheris.Setup([argv[0]] + argv[1:] + [corpus], target)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
