"""Unit tests for co3sop_nodes.common.errors: one root type for every core error."""

from __future__ import annotations

import inspect

import pytest

from co3sop_nodes.common import errors

SUBCLASSES = {
    "GridError": errors.Co3sopError,
    "CodecError": errors.Co3sopError,
    "UnknownCodecError": errors.CodecError,
    "CorruptPayloadError": errors.CodecError,
    "SizeMismatchError": errors.CodecError,
    "PayloadTooLargeError": errors.CodecError,
    "NonFiniteError": errors.CodecError,
    "DatasetError": errors.Co3sopError,
}


def test_root_is_an_exception():
    assert issubclass(errors.Co3sopError, Exception)
    assert not issubclass(errors.Co3sopError, (ValueError, TypeError, OSError))


@pytest.mark.parametrize("name,parent", list(SUBCLASSES.items()))
def test_hierarchy(name, parent):
    cls = getattr(errors, name)
    assert issubclass(cls, parent)
    assert issubclass(cls, errors.Co3sopError)


def test_every_error_class_is_listed():
    defined = {n for n, obj in inspect.getmembers(errors, inspect.isclass) if obj.__module__ == errors.__name__}
    assert defined == set(SUBCLASSES) | {"Co3sopError"}


def test_grid_and_codec_errors_are_separate():
    assert not issubclass(errors.GridError, errors.CodecError)
    assert not issubclass(errors.CodecError, errors.GridError)


def test_message_is_kept():
    with pytest.raises(errors.Co3sopError, match="values: bad"):
        raise errors.CorruptPayloadError("values: bad")
