"""One vocabulary: the same flag for the same concept in every command, lists written one way."""

from __future__ import annotations

import argparse

import pytest

from hogsa_loader.cli.main import build_parser

#: concept -> (its flag, spellings no command may use)
CONCEPTS = {
    "dataset root": ("--data", ("--data-root", "--root", "--dataset-root", "--data-dir")),
    "output folder": ("--out", ("--run-out", "--output", "--out-dir", "--output-dir")),
    "random seed": ("--seed", ("--run-seed", "--optim-seed", "--data-seed")),
    "torch device": ("--device", ("--run-device", "--optim-device")),
    "batch size": ("--batch-size", ("--optim-batch-size", "--optim-batch", "--pom-batch", "--batch", "--bs")),
    "subject": ("--subject", ("--data-subject", "--sid")),
    "subjects": ("--subjects", ("--data-subjects",)),
    "object": ("--object", ("--data-object", "--obj")),
    "sequences": ("--sequences", ("--data-sequences", "--seqs")),
    "dataset kind": ("--dataset", ("--data-dataset",)),
    "held-out subjects allowed": ("--allow-held-out", ("--data-allow-held-out",)),
    "background image folder": ("--background-folder", ("--backgrounds", "--bg-folder")),
    "CPU threads": ("--threads", ("--num-threads", "--torch-threads")),
}


def _train_parsers() -> dict[str, argparse.ArgumentParser]:
    import hogsa_loader.cli.train as t
    from hogsa_loader.cli import build_bundle, train_all_hogs
    from hogsa_loader.train.pom_config import ContactNetJobConfig, PoseBankConfig

    return {
        "hogsa train hogs": t.hogs_parser(),
        "hogsa train srm": t.srm_parser(),
        "hogsa train contactnet": t._job_parser("hogsa train contactnet", "", ContactNetJobConfig),
        "hogsa train bank": t._job_parser("hogsa train bank", "", PoseBankConfig),
        "train_all_hogs": train_all_hogs.build_parser(),
        "build_bundle": build_bundle.build_parser(),
    }


def _commands() -> dict[str, argparse.ArgumentParser]:
    out: dict[str, argparse.ArgumentParser] = {}

    def walk(parser: argparse.ArgumentParser, name: str) -> None:
        out[name] = parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub, sp in action.choices.items():
                    walk(sp, f"{name} {sub}")

    walk(build_parser(), "hogsa")
    out.update(_train_parsers())
    return out


@pytest.fixture(scope="module")
def commands() -> dict[str, argparse.ArgumentParser]:
    return _commands()


def _flags(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {o: a for a in parser._actions for o in a.option_strings if o.startswith("--")}


def test_every_command_is_seen(commands):
    assert {"hogsa export", "hogsa demo", "hogsa view", "hogsa train hogs", "hogsa train bank"} <= set(commands)
    assert len(commands) >= 16


def test_no_concept_has_two_spellings(commands):
    found = {}
    for name, parser in commands.items():
        for flag in _flags(parser):
            for concept, (canonical, others) in CONCEPTS.items():
                if flag in others:
                    found.setdefault(concept, []).append(f"{name}: {flag} (use {canonical})")
    assert found == {}


def test_the_concepts_are_spelled_where_they_occur(commands):
    """Each canonical flag is used by the commands that take the concept (a renamed concept
    would fail here, not silently pass the spelling test)."""
    seen = {flag for parser in commands.values() for flag in _flags(parser)}
    for concept, (canonical, _) in CONCEPTS.items():
        assert canonical in seen, concept
    for job in ("hogsa train hogs", "hogsa train srm", "hogsa train contactnet", "hogsa train bank"):
        assert {"--data", "--out", "--seed", "--batch-size"} <= set(_flags(commands[job])), job


def test_lists_are_one_comma_separated_value(commands):
    """No option takes several values after it (``--views 1 2``): lists are ``--views 1,2``;
    repeating a flag (``action='append'``) is not used either."""
    multi = [
        f"{name}: {flag}"
        for name, parser in commands.items()
        for flag, action in _flags(parser).items()
        if action.nargs not in (None, 0, "?") or isinstance(action, argparse._AppendAction)
    ]
    assert multi == []
    cfg = commands["hogsa train hogs"].parse_args(
        ["--data", "d", "--subject", "s01", "--object", "box", "--out", "o", "--views", "1,2,5"]
    )
    assert cfg.data__views == [1, 2, 5]


def test_each_training_job_names_itself_as_the_user_types_it(capsys):
    from hogsa_loader.cli.main import main

    for job in ("hogs", "srm", "contactnet", "bank"):
        with pytest.raises(SystemExit) as exc:
            main(["train", job, "--no-such-flag"])
        assert exc.value.code == 2
        assert capsys.readouterr().err.startswith(f"hogsa train {job}: error:"), job
