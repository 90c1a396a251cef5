"""The protocols' defaults as the help screens read them from source, against the imported
functions' signatures (the one source)."""

import importlib
import inspect

import pytest

from usf_graph.cli_defaults import per_task, source_defaults


@pytest.mark.parametrize("module", ["mnist", "det", "seg"])
def test_defaults_read_from_source_are_the_signatures(module):
    run = importlib.import_module(f"usf_graph.train.{module}").run
    signature = {k: p.default for k, p in inspect.signature(run).parameters.items()
                 if p.default is not inspect.Parameter.empty}
    read = source_defaults(module)
    assert read and read.items() <= signature.items()
    # left out: a call (tuple(MODELS)) and an imported name (FOV_SHARE); the module's own
    # constants (FOV_EPOCHS) are read
    left = set(signature) - set(read)
    assert left <= {"models", "fov_share"}, left
    assert module == "mnist" or read["fov_epochs"] == importlib.import_module(
        f"usf_graph.train.{module}").FOV_EPOCHS


def test_help_names_each_protocols_default():
    det, seg = source_defaults("det"), source_defaults("seg")
    assert per_task("lr") == f"det {det['lr']:g}, seg {seg['lr']:g}" == "det 0.002, seg 0.003"
    assert per_task("num_test") == f"det/seg {det['num_test']}"
    assert per_task("channel_scale") == "det/seg 1"
    with pytest.raises(LookupError, match="no function fit"):
        source_defaults("seg", "fit")


def test_keyword_only_defaults_and_constants_are_read(tmp_path, monkeypatch):
    import usf_graph.cli_defaults as cd

    (tmp_path / "demo.py").write_text("EPOCHS = 6\nNAME = 'x'.upper()\n\n"
                                      "def run(a, b=2, *, c, d=EPOCHS, e=NAME, f=(1, 'two')):\n    pass\n")
    monkeypatch.setattr(cd, "_TRAIN", tmp_path)
    assert cd.source_defaults.__wrapped__("demo") == {"b": 2, "d": 6, "f": (1, "two")}
