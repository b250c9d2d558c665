#!/usr/bin/env python3
"""Hand-written mutants of the Python modules (tools/py_mutants.yaml), one at a time: write the mutated file, run
its tests (stop at the first failure), write the original back (also on Ctrl-C or SIGTERM). Prints killed, survived
or stale per mutant; exits non-zero when one survived or went stale. `make mutate` runs it after cosmic-ray."""
import signal
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
MUTANTS = Path(__file__).resolve().parent / "py_mutants.yaml"
TIMEOUT_S = 600


def main() -> int:
    with open(MUTANTS) as stream:
        mutants = yaml.safe_load(stream)
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    bad = 0
    for mutant in mutants:
        path = ROOT / mutant["file"]
        original = path.read_text()
        if original.count(mutant["find"]) != 1:
            print(f"STALE    {mutant['name']}: `find` occurs {original.count(mutant['find'])} times in {mutant['file']}")
            bad += 1
            continue
        run = None
        try:
            path.write_text(original.replace(mutant["find"], mutant["replace"]))
            run = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
                                  *mutant["tests"]], cwd=ROOT, capture_output=True, text=True, timeout=TIMEOUT_S)
            killed = run.returncode != 0
        except subprocess.TimeoutExpired:
            killed = True   # a mutant that hangs the tests is caught by them
        finally:
            path.write_text(original)
        failed = "timed out" if run is None else \
            next((line for line in run.stdout.splitlines() if line.startswith("FAILED")), "") if killed else ""
        print(f"{'KILLED  ' if killed else 'SURVIVED'} {mutant['name']}: {mutant['why']}"
              + (f"\n         {failed}" if failed else ""), flush=True)
        bad += not killed
    print(f"hand mutants: {len(mutants) - bad} of {len(mutants)} killed")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
