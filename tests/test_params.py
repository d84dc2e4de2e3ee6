"""Params: every field checked when it is made, on the writer's side and the reader's alike.

A file states its Params (PARM), and the reader builds them with the same checks, so a
limit placed here holds for both: the writer refuses before any work what the reader
would refuse after all of it.
"""

from __future__ import annotations

import re

import pytest

import dftpcc
from dftpcc import format as fmt
from dftpcc import params
from dftpcc.errors import CorruptFileError, InvalidInputError

from .fuzz import craft
from .fuzz.seeds import seed_files


def test_the_coordinate_limit_has_one_home():
    assert fmt.validate.MAX_COORDINATE_M is params.MAX_COORDINATE_M == 1e12


@pytest.mark.parametrize("field", ["step", "target_rmse", "target_max_error"])
@pytest.mark.parametrize("value", [1e300, 2e12, float("inf")])
def test_a_height_beyond_what_a_file_holds_is_refused(field, value):
    with pytest.raises(InvalidInputError, match=rf"{field}.* at most 1e\+12 m.*got {re.escape(repr(value))}"):
        dftpcc.make_params(resolution=1.0, **{field: value})


@pytest.mark.parametrize("field", ["step", "target_rmse", "target_max_error"])
def test_the_limit_itself_is_allowed(field):
    assert getattr(dftpcc.make_params(resolution=1.0, **{field: 1e12}), field) == 1e12


def test_a_bits_per_point_target_has_no_height_limit():
    assert dftpcc.make_params(resolution=1.0, target_bpp=1e300).target_bpp == 1e300


@pytest.mark.parametrize("field,value", [("step", 1e13), ("target_max_error", 1e300)])
def test_the_reader_applies_the_same_limit(field, value):
    good = seed_files()["compact_max_error"]
    parm = craft.json_of(good, b"PARM")
    parm[field] = value
    with pytest.raises(CorruptFileError, match=rf"parameter section is invalid: .*at most 1e\+12 m"):
        dftpcc.open(craft.with_json(good, b"PARM", parm))
