"""`offload-cloud-learner`: the fleet learner service and the operator's commands on its store.

    offload-cloud-learner serve --bind tcp://0.0.0.0:5556 --keys-dir KEYS --store DIR [...]
    offload-cloud-learner list|status --store DIR
    offload-cloud-learner pin VERSION [--robot NAME] --store DIR
    offload-cloud-learner rollback [--robot NAME] --store DIR
    offload-cloud-learner unpin [--robot NAME] --store DIR
    offload-cloud-learner import MODEL [--publish] --store DIR

The commands act on the store's files (atomic writes under a lock); a running service picks the change up at the
next robot's query."""
import argparse
import json
import logging
import signal
import sys
import threading

from offload_cloud.cli_args import bounded_float, bounded_int
from offload_cloud.server_cli import _endpoint, metrics_bind


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="offload-cloud-learner", description="Fleet learner (ROS-free).")
    commands = parser.add_subparsers(dest="command", required=True)
    serve = commands.add_parser("serve", help="run the service")
    serve.add_argument("--bind", type=_endpoint, default="tcp://0.0.0.0:5556", help="endpoint (default port 5556)")
    serve.add_argument("--keys-dir", help="server keys dir (server.key_secret, clients/): the robots' allowlist")
    serve.add_argument("--insecure", action="store_true", help="plaintext, every robot named 'insecure'")
    serve.add_argument("--store", required=True, help="store directory (models, history, state, pool)")
    serve.add_argument("--pool", default="", help="experience pool directory (default STORE/pool)")
    serve.add_argument("--seed-bag", help="a learning run's bag, pooled once as the robot _seed")
    serve.add_argument("--train-every-rows", type=bounded_int("--train-every-rows", 1, 10 ** 9), default=200)
    serve.add_argument("--train-every-s", type=bounded_float("--train-every-s", 0.1, 86400 * 7), default=300.0)
    serve.add_argument("--window-rows", type=bounded_int("--window-rows", 10, 10 ** 7), default=2000,
                       help="recent requests per robot a round reads")
    serve.add_argument("--holdout", type=bounded_float("--holdout", 0.05, 0.95), default=0.3,
                       help="share of each robot's window kept out of training to gate on")
    serve.add_argument("--min-robot-rows", type=bounded_int("--min-robot-rows", 2, 10 ** 7), default=20)
    serve.add_argument("--gate-margin-ms", type=bounded_float("--gate-margin-ms", 0.0, 1e6), default=0.0,
                       help="slower on average by at most this still counts as not worse (default 0)")
    serve.add_argument("--epochs", type=bounded_float("--epochs", 0.01, 1e4), default=50.0)
    serve.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="any DQNConfig field")
    serve.add_argument("--bag-mib", type=bounded_float("--bag-mib", 0.01, 1 << 20), default=16.0)
    serve.add_argument("--disk-mib", type=bounded_float("--disk-mib", 0.01, 1 << 30), default=1024.0)
    serve.add_argument("--robot-disk-mib", type=bounded_float("--robot-disk-mib", 0.01, 1 << 30), default=256.0)
    serve.add_argument("--rows-per-s", type=bounded_float("--rows-per-s", 0.0, 1e6), default=50.0,
                       help="per key; 0 disables (with --kib-per-s)")
    serve.add_argument("--rows-burst", type=bounded_float("--rows-burst", 1.0, 1e9), default=2048.0)
    serve.add_argument("--kib-per-s", type=bounded_float("--kib-per-s", 0.0, 1e9), default=256.0)
    serve.add_argument("--burst-mib", type=bounded_float("--burst-mib", 0.01, 1 << 20), default=16.0)
    serve.add_argument("--metrics-bind", type=metrics_bind, metavar="HOST:PORT",
                       help="serve Prometheus metrics (the STATS counters) at http://HOST:PORT/metrics; port 0 picks a "
                            "free one. Unauthenticated: bind a private address (default: off)")
    serve.add_argument("--log-level", default="INFO")
    for name in ("list", "status", "unpin", "rollback", "pin"):
        command = commands.add_parser(name, help=f"{name} (acts on the store)")
        command.add_argument("--store", required=True)
        if name == "pin":
            command.add_argument("version")
        if name in ("pin", "rollback", "unpin"):
            command.add_argument("--robot", help="one robot (its allowlist name); default: the fleet")
    imports = commands.add_parser("import", help="add a model (retrain's checkpoint.pt or a model .npz) to the store")
    imports.add_argument("model", help="a learner checkpoint (checkpoint.pt) or a model file (.npz)")
    imports.add_argument("--store", required=True)
    imports.add_argument("--publish", action="store_true",
                         help="make it the fleet's current version (training continues from it)")
    args = parser.parse_args(argv)
    if args.command == "serve" and not args.insecure and not args.keys_dir:
        parser.error("pass --keys-dir (CURVE with the robots' allowlist) or --insecure")
    return args


def learner_config(args):
    from offload_cloud.learner.pool import PoolLimits
    from offload_cloud.learner.service import LearnerConfig
    from offload_cloud.learner.training import TrainingConfig
    from offload_learner_py.core.config import DQNConfig
    from offload_learner_py.offline.retrain import parse_overrides

    overrides = parse_overrides(args.set)
    DQNConfig.from_dict(overrides)   # refused here, before anything starts
    mib = 1 << 20
    limits = PoolLimits(int(args.bag_mib * mib), int(args.disk_mib * mib), int(args.robot_disk_mib * mib),
                        args.rows_per_s, args.rows_burst, args.kib_per_s * 1024 if args.rows_per_s else 0.0,
                        args.burst_mib * mib)
    training = TrainingConfig(args.window_rows, args.holdout, args.min_robot_rows, args.gate_margin_ms / 1000.0,
                              args.epochs, overrides)
    return LearnerConfig(args.bind, args.store, args.pool, args.keys_dir, args.insecure, args.seed_bag,
                         args.train_every_rows, args.train_every_s, limits, training, metrics_bind=args.metrics_bind)


def serve(args) -> int:
    import torch

    from offload_cloud.learner.service import LOG, FleetLearner

    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)
    try:
        learner = FleetLearner(learner_config(args))
        print(f"listening on {learner.start()}", flush=True)
        if learner.metrics is not None:
            print(f"metrics on http://{learner.metrics.address}/metrics", flush=True)
    except (OSError, ValueError, TypeError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    signal.signal(signal.SIGHUP, lambda *_: learner.reload_keys())
    while not done.wait(1.0):
        pass
    learner.stop()
    LOG.info("fleet learner stopped")
    return 0


def model_file_of(path: str) -> bytes:
    """The model file bytes of `path`: a model file as it is, or a learner checkpoint (retrain's, a learning run's)
    converted, both read by the loaders that refuse hostile files. StoreError when it is neither."""
    from offload_cloud.learner.store import StoreError
    from offload_learner_py.core.checkpoint import load_checkpoint
    from offload_learner_py.core.model_file import MAX_MODEL_BYTES, ModelFileError, agent_model_bytes, load_model

    try:
        with open(path, "rb") as source:
            data = source.read(MAX_MODEL_BYTES + 1)
    except OSError as error:
        raise StoreError(f"{path}: {error.strerror or error}") from None
    try:
        load_model(data)
        return data
    except ModelFileError as as_model:
        try:
            return agent_model_bytes(load_checkpoint(path))
        except (ValueError, RuntimeError, OSError) as as_checkpoint:
            raise StoreError(f"{path} is neither a model file ({as_model}) nor a learner checkpoint "
                             f"({as_checkpoint})") from None


def history_line(entry: dict) -> str:
    """`list`'s line of a trained round or an operator's import."""
    head = f"{entry['version'][:16]} parent {entry.get('parent', '')[:16] or '-':16} "
    if entry.get("event") == "imported":
        published = "published" if entry.get("published") else "stored   "
        return head + f"{published} imported from {entry.get('source', '?')}"
    gate = " ".join(f"{robot}:{gate_word(g)}" for robot, g in entry["gate"].items())
    return head + f"{'published' if entry['published'] else 'refused  '} rows {sum(entry['rows'].values())} {gate}"


def gate_word(figure: dict) -> str:
    """A robot's verdict on a candidate: ok, no, or n/a when its rows could not judge it (it abstained)."""
    if figure.get("accepted"):
        return "ok"
    return "n/a" if figure.get("judged") is False else "no"


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.command == "serve":
        return serve(args)
    from offload_cloud.learner.store import ModelStore, StoreError

    store = ModelStore(args.store)
    try:
        if args.command == "list":
            for entry in store.history():
                if entry.get("event") in ("trained", "imported"):
                    print(history_line(entry))
            return 0
        if args.command == "status":
            print(json.dumps(store.summary(), indent=2, sort_keys=True))
            return 0
        state = {"pin": lambda: store.pin(args.version, args.robot), "rollback": lambda: store.rollback(args.robot),
                 "unpin": lambda: store.unpin(args.robot),
                 "import": lambda: store.import_model(model_file_of(args.model), args.model, args.publish),
                 }[args.command]()
    except StoreError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(json.dumps(state, indent=2, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
