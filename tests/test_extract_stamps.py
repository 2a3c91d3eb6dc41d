"""Header stamps -> ns: one conversion (extract/convert.py ``header_stamp_ns``) for extract, VO and loops."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from skidbench.pipeline.extract.convert import header_stamp_ns
from skidbench.pipeline.extract.synthetic import _Factory, typestore_for

BAG_NS = 1_700_000_000_123_456_789


def _msg(**stamp):
    return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(**stamp)))


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_a_rosbags_header_stamp_is_exact_integer_nanoseconds(fmt):
    f = _Factory(typestore_for(fmt))
    stamp = 1_700_000_000_999_999_999  # 19 digits: float64 would round it
    msg = SimpleNamespace(header=f.header(stamp, "base_link"))
    assert header_stamp_ns(msg, BAG_NS) == stamp


def test_a_ros1_nsec_field_is_read_like_nanosec():
    assert header_stamp_ns(_msg(sec=12, nsec=345), BAG_NS) == 12_000_000_345
    assert header_stamp_ns(_msg(sec=12, nanosec=345), BAG_NS) == 12_000_000_345


UNSET = [{"sec": 0, "nanosec": 0}, {"sec": 0, "nsec": 0}, {"sec": -1, "nanosec": 5}]


@pytest.mark.parametrize("stamp", UNSET)
def test_an_unset_or_pre_epoch_stamp_falls_back_to_the_bag_time(stamp):
    assert header_stamp_ns(_msg(**stamp), BAG_NS) == BAG_NS


def test_the_smallest_positive_stamp_is_kept():
    assert header_stamp_ns(_msg(sec=0, nanosec=1), BAG_NS) == 1
