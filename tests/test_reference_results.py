"""The study's committed reference results (docs/results/<profile>/, written by
``python -m kpstudy publish``): each report's tables load, the figures it shows exist,
its stamp names the commit and command, and the standard profile's tables have the seeds
a finding needs."""

import re
from pathlib import Path

import pandas as pd
import pytest

from kpstudy.study.report import COMPARED

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
REFERENCES = sorted(p.parent for p in RESULTS.glob("*/REPORT.md"))


def test_the_standard_profile_is_the_reference_result():
    assert RESULTS / "standard" in REFERENCES


@pytest.mark.parametrize("reference", REFERENCES, ids=lambda p: p.name)
def test_every_table_loads_and_every_figure_shown_exists(reference):
    report = (reference / "REPORT.md").read_text()
    tables = sorted((reference / "tables").glob("*.csv"))
    assert tables
    for path in tables:
        frame = pd.read_csv(path)
        assert len(frame) and len(frame.columns), path.name
    shown = re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", report)
    assert shown
    for target in shown:
        assert (reference / target).is_file(), target
    for target in re.findall(r"\]\((tables/[^)\s]+)\)", report):
        assert (reference / target).is_file(), target


@pytest.mark.parametrize("reference", REFERENCES, ids=lambda p: p.name)
def test_the_stamp_names_the_commit_and_the_command(reference):
    stamp = (reference / "STAMP.md").read_text()
    assert re.search(r"- commit: `[0-9a-f]{7,40}`", stamp)
    assert re.search(rf"- command: `[^`]*--profile {reference.name}[^`]*`", stamp)


def test_the_standard_tables_rest_on_50_seeds():
    for name in COMPARED:
        records = pd.read_csv(RESULTS / "standard" / "tables" / f"{name}_records.csv")
        seeds = records.groupby("model")["image_id"].nunique()
        assert (seeds >= 50).all(), (name, seeds.to_dict())
