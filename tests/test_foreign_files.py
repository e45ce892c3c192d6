"""Published YAML and pickles are read as plain data; a file that asks for code is refused
with its name, and nothing of it runs."""

import os
import pickle

import numpy as np
import pytest

from torchhand.io.foreign_files import ForeignFileError, read_pickle, read_yaml

RAN = []


def _record(*args):  # what a crafted pickle or YAML would call
    RAN.append(args)


class _Evil:
    def __reduce__(self):
        return (_record, ("pickle ran",))


def test_yaml_tuples_are_lists_and_other_python_tags_are_refused(tmp_path):
    good = tmp_path / "extrinsics.yml"
    good.write_text("master: '840412060917'\nextrinsics:\n  '840412060917': !!python/tuple [1.0, 0.0, 0.0, 0.5]\n"
                    "  'other': [0.0, 1.0, 0.0, -0.2]\n")
    data = read_yaml(good)
    assert data["extrinsics"]["840412060917"] == [1.0, 0.0, 0.0, 0.5] and data["master"] == "840412060917"
    for tag in ("!!python/object/apply:os.system ['echo ran']", "!!python/name:os.system", "!!python/object:object {}"):
        bad = tmp_path / "bad.yml"
        bad.write_text(f"key: {tag}\n")
        with pytest.raises(ForeignFileError, match=r"bad\.yml: could not determine a constructor"):
            read_yaml(bad)
    broken = tmp_path / "broken.yml"
    broken.write_text("key: [1, 2\n")
    with pytest.raises(ForeignFileError, match=r"broken\.yml: not a YAML file"):
        read_yaml(broken)


@pytest.mark.parametrize("protocol", [2, pickle.HIGHEST_PROTOCOL])
def test_pickles_of_containers_and_arrays_are_read(tmp_path, protocol):
    meta = {"handJoints3D": np.arange(63, dtype=np.float64).reshape(21, 3), "camMat": np.eye(3, dtype=np.float32),
            "objName": "003_cracker_box", "handBeta": [0.1, 0.2], "ids": {1, 2}, "scale": np.float32(2.5)}
    path = tmp_path / "0000.pkl"
    path.write_bytes(pickle.dumps(meta, protocol=protocol))
    back = read_pickle(path)
    assert back.keys() == meta.keys() and back["objName"] == "003_cracker_box" and back["ids"] == {1, 2}
    assert np.array_equal(back["handJoints3D"], meta["handJoints3D"]) and back["camMat"].dtype == np.float32
    assert back["scale"] == np.float32(2.5)


def test_a_crafted_pickle_is_refused_and_never_runs(tmp_path):
    RAN.clear()
    for payload, asked in ((_Evil(), "_record"), ({"a": _Evil()}, "_record")):
        path = tmp_path / "crafted.pkl"
        path.write_bytes(pickle.dumps(payload, protocol=2))
        with pytest.raises(ForeignFileError, match=rf"crafted\.pkl: the pickle asks for .*{asked}; only builtin"):
            read_pickle(path)
    path.write_bytes(pickle.dumps(os.system, protocol=2))
    with pytest.raises(ForeignFileError, match=r"asks for (posix|nt)\.system"):
        read_pickle(path)
    assert RAN == []
    junk = tmp_path / "junk.pkl"
    junk.write_bytes(b"not a pickle at all")
    with pytest.raises(ForeignFileError, match=r"junk\.pkl: not a readable pickle"):
        read_pickle(junk)
