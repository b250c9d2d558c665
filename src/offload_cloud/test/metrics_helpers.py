"""Scraping a Prometheus endpoint the way Prometheus does (HTTP GET /metrics, the text format parsed by
prometheus_client's own parser), for the metrics tests of the cloud server and the fleet learner."""
import urllib.request

from prometheus_client.parser import text_string_to_metric_families


def scrape_text(address: str) -> str:
    with urllib.request.urlopen(f"http://{address}/metrics", timeout=10) as response:
        assert response.status == 200
        return response.read().decode()


def samples(text: str) -> dict:
    """(sample name, sorted label items) -> value of every sample in an exposition."""
    return {(sample.name, tuple(sorted(sample.labels.items()))): sample.value
            for family in text_string_to_metric_families(text) for sample in family.samples}


def scrape(address: str) -> dict:
    return samples(scrape_text(address))


def value(figures: dict, name: str, **labels) -> float:
    """A sample's value; 0 when absent (a labelled counter appears once it has counted)."""
    return figures.get((name, tuple(sorted(labels.items()))), 0.0)


def moved(before: dict, after: dict, name: str, **labels) -> float:
    return value(after, name, **labels) - value(before, name, **labels)
