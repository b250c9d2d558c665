"""The offline benchmark runs end to end on tiny bags and prints its measured figures (no timing is
judged here: speed is the benchmark's business, on a quiet machine)."""
from offload_demos import bench_offline as bench_offline


def test_benchmark_prints_ingest_and_training_rates(capsys):
    status = bench_offline.main(["--bags", "2", "--requests", "300", "--steps", "20", "--workers", "2"])
    out = capsys.readouterr().out
    assert status in (0, 2)
    ingest = [line for line in out.splitlines() if line.startswith("ingest")]
    assert len(ingest) == 2 and all("transitions/s" in line for line in ingest)
    assert "(600 transitions, 450 with both latencies)" in ingest[1]
    training = next(line for line in out.splitlines() if line.startswith("offline training"))
    assert "steps/s" in training and "20 steps on 225 rows" in training
