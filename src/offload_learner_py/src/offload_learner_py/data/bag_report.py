"""What reading bags found, bounded per bag whatever a bag holds: topics are listed up to MAX_LISTED_TOPICS
(the most messages first; the rest as two counts), the learner's latched settings up to MAX_CONFIGS distinct
ones, and every example or error clipped to MAX_TEXT characters. A bag of 250,000 junk connections once
made a 4.75 MB terminal line and 17 MB of report files."""
from dataclasses import asdict, dataclass, field
from typing import Dict, List

from offload_learner_py.data.records import PairingCounts

MAX_LISTED_TOPICS = 20
MAX_CONFIGS = 32
MAX_TEXT = 300


def clip(text: str, limit: int = MAX_TEXT) -> str:
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


@dataclass
class BagReport(PairingCounts):
    """What one bag held and what became of it (the pairing counts, and the reading's own)."""
    path: str = ""
    ok: bool = True
    error: str = ""
    indexed: bool = True
    recovered_note: str = ""          # how an unindexed or cut-off bag was read
    topics: Dict[str, int] = field(default_factory=dict)   # messages per topic that was read (listed ones)
    ignored_topics: Dict[str, int] = field(default_factory=dict)   # messages per skipped topic (listed ones)
    other_topics: int = 0             # topics beyond the listed ones (read or skipped)
    other_topic_messages: int = 0     # and their messages
    undecodable: int = 0              # messages that do not decode with their own definition
    damaged_chunks: int = 0           # chunks that do not decompress (their messages are lost)
    definitions: Dict[str, str] = field(default_factory=dict)   # message type -> md5 of the bag's definition
    configs: List[dict] = field(default_factory=list)   # the learner's distinct settings (sessions, and changes made
                                                        # on the running node), each with since_ns: first recorded
    other_configs: int = 0            # settings messages past MAX_CONFIGS distinct ones, not kept

    def note(self, example: str) -> None:
        super().note(clip(example))

    def list_topics(self, name: str, counts: Dict[str, int]) -> None:
        """Keep the MAX_LISTED_TOPICS topics with the most messages in `name` (topics or ignored_topics)."""
        ranked = sorted(counts.items(), key=lambda item: (-item[1], item[0]))
        setattr(self, name, {clip(topic): count for topic, count in sorted(ranked[:MAX_LISTED_TOPICS])})
        self.other_topics += max(0, len(ranked) - MAX_LISTED_TOPICS)
        self.other_topic_messages += sum(count for _, count in ranked[MAX_LISTED_TOPICS:])

    def add_config(self, values: dict, since_ns: int = 0) -> None:
        """One session's settings, or a change made on the running node (dynamic_reconfigure), unless the same (NaN
        equal to NaN) are kept already; `since_ns`: the message's stamp (else its time in the bag), so an analysis
        knows from when on the requests ran under them."""
        values = {key: clip(value) if isinstance(value, str) else value for key, value in values.items()}
        seen = self.__dict__.setdefault("_config_keys", set())   # not a field: not in the report's dict
        if repr(values) in seen:
            return
        if len(self.configs) < MAX_CONFIGS:
            seen.add(repr(values))
            self.configs.append({**values, "since_ns": since_ns})
        else:
            self.other_configs += 1


@dataclass
class ReadReport:
    bags: List[BagReport]
    duplicates_across_bags: int = 0   # identical requests found in two bags (kept once)
    id_collisions: int = 0            # same request id, different content, in two bags (both kept)

    @property
    def failed(self) -> List[BagReport]:
        return [bag for bag in self.bags if not bag.ok]

    def total(self, name: str) -> int:
        return sum(getattr(bag, name) for bag in self.bags)

    def recorded(self, name: str) -> list:
        """The distinct values of one LearnerConfig field over every session in the bags."""
        values = []
        for bag in self.bags:
            for config in bag.configs:
                if config.get(name) not in values:
                    values.append(config.get(name))
        return values

    def to_dict(self) -> dict:
        return {"bags": [asdict(bag) for bag in self.bags], "duplicates_across_bags": self.duplicates_across_bags,
                "id_collisions": self.id_collisions}

    def format(self) -> str:
        lines = []
        for bag in self.bags:
            if not bag.ok:
                lines.append(f"FAILED {clip(bag.error, 2 * MAX_TEXT)}")
                continue
            lines.append(f"{bag.path}: {bag.decisions} decisions, {bag.outcomes} outcomes -> {bag.requests} "
                         f"requests ({bag.rewarded_steps} with both latencies, {bag.one_latency_steps} with one)")
            if not bag.indexed:
                lines.append(f"  {clip(bag.recovered_note, 2 * MAX_TEXT)}")
            skipped = [f"{count} {what}" for count, what in (
                (bag.dropped_no_outcome, "decisions without outcome dropped"),
                (bag.orphan_outcomes, "outcomes without decision dropped"),
                (bag.duplicate_decisions, "duplicate decisions dropped"),
                (bag.duplicate_outcomes, "duplicate outcomes dropped"),
                (bag.invalid, "invalid requests dropped"),
                (bag.undecodable, "undecodable messages dropped"),
                (bag.damaged_chunks, "damaged chunks skipped"),
                (bag.other_configs, "learner settings past the first 32 distinct ones not kept")) if count]
            if skipped:
                lines.append("  skipped: " + ", ".join(skipped))
            for example in bag.invalid_examples[:5]:
                lines.append(f"    e.g. {clip(example)}")
            if bag.ignored_topics:
                lines.append("  ignored topics: " + ", ".join(f"{clip(topic, 80)} ({count})" for topic, count in
                                                           sorted(bag.ignored_topics.items())[:MAX_LISTED_TOPICS]))
            if bag.other_topics:
                lines.append(f"  and {bag.other_topics} more topics ({bag.other_topic_messages} messages), not listed")
        read = [bag for bag in self.bags if bag.ok]
        lines.append(f"read {len(read)}/{len(self.bags)} bags: {self.total('requests')} requests, "
                     f"{self.total('rewarded_steps')} transitions with both latencies, "
                     f"{self.total('one_latency_steps')} with one latency")
        if self.duplicates_across_bags or self.id_collisions:
            lines.append(f"across bags: {self.duplicates_across_bags} duplicate requests kept once, "
                         f"{self.id_collisions} request ids reused with different content (both kept)")
        return "\n".join(lines)
