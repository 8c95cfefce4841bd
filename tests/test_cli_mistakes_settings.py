"""Settings files from other editors and --set values at their edges, through the CLI: a
UTF-16 file as Notepad saves it (read), bytes of another encoding, a value nested thousands
deep, a missing path or a folder given as --config, a key set twice (a warning), a working
scale too large. Each gives the right result or one line naming the file, item or key, exit
2, nothing written.
"""
from __future__ import annotations

import pytest
from test_cli_mistakes import TINY_SET, command_argv, one_line_error, run_cli
from test_cli_mistakes import frames as frames  # noqa: PLC0414 - fixtures the tests take
from test_cli_mistakes import mesh as mesh  # noqa: PLC0414
from test_cli_mistakes import predictions as predictions  # noqa: PLC0414
from test_cli_mistakes import train_data as train_data  # noqa: PLC0414
from test_cli_mistakes import weights as weights  # noqa: PLC0414

#: The commands with --config, each with a valid invocation (test_cli_mistakes.command_argv).
CONFIG_COMMANDS = ("infer", "synth", "train", "demo", "export")
SETTING = {"infer": ("decode", "threshold", 0.2), "synth": ("target", "count", [1, 1]),
           "train": ("train", "lr", 0.002), "demo": ("decode", "threshold", 0.2),
           "export": ("export", "opset", 18)}


def argv_with(command, tmp_path, fixtures, *extra) -> tuple[list, object]:
    out = tmp_path / ("model.onnx" if command == "export" else "out")
    return [*command_argv(command, out, *fixtures), *extra], out


@pytest.fixture
def fixtures(frames, weights, mesh, predictions, train_data):
    return frames, weights, mesh, predictions, train_data


def yaml_text(command: str) -> str:
    section, key, value = SETTING[command]
    return f"{section}:\n  {key}: {value}\n"


@pytest.mark.parametrize("command", CONFIG_COMMANDS)
def test_a_config_in_utf16_as_notepad_saves_it_is_read(command, tmp_path, capsys):
    """The settings of a UTF-16 file (with its byte order mark) are those of the same file in
    UTF-8, which differ from the defaults."""
    printed = []
    for encoding in ("utf-16", "utf-8", None):
        cfg = tmp_path / f"mine-{encoding}.yaml"
        cfg.write_text(yaml_text(command), encoding=encoding or "utf-8")
        code, out, err = run_cli(["settings", command] + (["--config", cfg] if encoding else []), capsys)
        assert code == 0, err
        printed.append(out)
    assert printed[0] == printed[1] != printed[2]


@pytest.mark.parametrize("command", CONFIG_COMMANDS)
def test_a_config_of_another_encoding_is_one_line(command, fixtures, tmp_path, capsys):
    cfg = tmp_path / "latin.yaml"
    cfg.write_bytes("# café\n".encode("latin-1") + yaml_text(command).encode())
    argv, out = argv_with(command, tmp_path, fixtures, "--config", cfg)
    line = one_line_error(*run_cli(argv, capsys)[::2], command)
    assert f"{cfg}: not UTF-8 or UTF-16 text (invalid continuation byte at byte 5); save it as UTF-8" in line
    assert not out.exists()


def test_a_set_value_nested_thousands_deep_is_one_line(fixtures, tmp_path, capsys):
    item = "decode.threshold=" + "[" * 3000 + "]" * 3000
    argv, out = argv_with("infer", tmp_path, fixtures, "--set", item)
    line = one_line_error(*run_cli(argv, capsys)[::2], "infer")
    assert line.endswith(": nested deeper than 32 levels") and "--set decode.threshold=[[[" in line
    assert len(line) < 300 and not out.exists()


def test_a_config_file_nested_too_deep_is_one_line(fixtures, tmp_path, capsys):
    cfg = tmp_path / "deep.yaml"
    cfg.write_text("decode:\n  threshold: " + "[" * 40 + "]" * 40 + "\n")
    argv, out = argv_with("infer", tmp_path, fixtures, "--config", cfg)
    line = one_line_error(*run_cli(argv, capsys)[::2], "infer")
    assert f"{cfg}: nested deeper than 32 levels" in line
    assert not out.exists()


@pytest.mark.parametrize("given, expected", [
    ("./my_settings", "./my_settings: config file not found"),
    ("{tmp}/folder.yaml", "{tmp}/folder.yaml: config file is a folder, not a YAML file"),
    ("{tmp}/folder", "{tmp}/folder: config file is a folder, not a YAML file"),
    ("my_settings", "unknown config 'my_settings'; known: demo, "),
])
def test_a_config_path_that_is_missing_or_a_folder_says_so(given, expected, fixtures, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "folder.yaml").mkdir()
    (tmp_path / "folder").mkdir()
    argv, out = argv_with("infer", tmp_path, fixtures, "--config", given.format(tmp=tmp_path))
    line = one_line_error(*run_cli(argv, capsys)[::2], "infer")
    assert expected.format(tmp=tmp_path) in line
    assert not out.exists()


@pytest.mark.parametrize("command", ["infer", "train"])
def test_a_key_set_twice_in_a_config_takes_the_last_and_says_so(command, tmp_path, capsys):
    cfg = tmp_path / "twice.yaml"
    section, key, value = SETTING[command]
    cfg.write_text(f"{section}:\n  {key}: {value}\n  {key}: {value}\n")
    code, out, err = run_cli(["settings", command, "--config", cfg], capsys)
    assert code == 0, err
    assert err.splitlines() == [f"dope-hope settings: warning: {cfg}: line 3 sets '{key}' again (first on line 2); "
                                "the last value is taken"]


def test_a_working_scale_too_large_names_the_scale(fixtures, tmp_path, capsys):
    argv, out = argv_with("infer", tmp_path, fixtures, "--set", "multiscale.scales=[1,100]")
    line = one_line_error(*run_cli(argv, capsys)[::2], "infer")
    assert ("a 80x64 image would be resized to 6375x5100 for the network, beyond 4096 pixels; multiscale.scales "
            "holds 100 (times the working height of 51 px): give a smaller scale") in line
    assert not line.endswith("give a smaller height") and not out.exists()


def test_train_takes_a_utf16_recipe(train_data, tmp_path, capsys):
    """The recipe a training run records is the UTF-16 file's."""
    import torch

    cfg = tmp_path / "recipe.yaml"
    cfg.write_text("train:\n  lr: 0.002\n", encoding="utf-16")
    out = tmp_path / "run"
    code, _, err = run_cli(["train", "--data", train_data, "--object", "Ketchup", "--out", out, "--steps", 1,
                            "--no-progress", "--config", cfg, "--set", *TINY_SET], capsys)
    assert code == 0, err
    assert torch.load(out / "last.pt", weights_only=True)["config"]["train"]["lr"] == 0.002
