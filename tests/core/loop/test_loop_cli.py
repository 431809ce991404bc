"""``neb-slam vocab train`` and ``neb-slam vocab info`` on a tiny training set."""

from __future__ import annotations

import numpy as np

from neb_slam_core.cli.main import main
from neb_slam_core.loop.vocabulary import Vocabulary


def test_vocab_train_is_reproducible_and_info_reads_it(tmp_path, capsys):
    args = ["--scenes", "2", "--frames", "2", "--size", "160x120", "--k", "4", "--depth", "2", "--seed", "3"]
    assert main(["vocab", "train", str(tmp_path / "a.npz"), *args]) == 0
    assert main(["vocab", "train", str(tmp_path / "b.npz"), *args]) == 0
    a, b = Vocabulary.load(tmp_path / "a.npz"), Vocabulary.load(tmp_path / "b.npz")
    assert np.array_equal(a.centres, b.centres) and np.array_equal(a.idf, b.idf)
    assert (a.branching, a.depth) == (4, 2) and 4 < a.n_words <= 16
    assert a.training.n_images == 4 and a.training.seed == 3 and "seeds 1000..1001" in a.training.source
    capsys.readouterr()
    assert main(["vocab", "info", str(tmp_path / "a.npz")]) == 0
    out = capsys.readouterr().out
    assert "k=4, L=2" in out and "4 images" in out and "load time" in out


def test_vocab_info_of_a_bad_file_is_an_error_naming_it(tmp_path, capsys):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"nope")
    assert main(["vocab", "info", str(bad)]) == 2
    assert "bad.npz: not a vocabulary file" in capsys.readouterr().err
