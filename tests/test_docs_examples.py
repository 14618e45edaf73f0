"""Every documented example runs as written: README.md's, and every command's --help Examples.

README's examples run in order in one temporary folder; the --help examples
of all commands run in order (the data flow: pointings, catalog, render,
apply-persistence, measure, correlate, budget, diagnose, study, man) in
another, each chain building on its earlier outputs, as a reader would.
Both folders start with the sample data and (links to) the real inputs of
../shared/data; examples naming a shared input that is absent are skipped,
every other one must exit 0 and write outputs no earlier example wrote.
"""

from pathlib import Path

import pytest

from conftest import SHARED_DATA
import docexamples as docs

HELP_ORDER = ("pointings", "catalog", "render", "apply-persistence", "measure", "correlate", "budget", "diagnose",
              "study", "man", "completion")


def _check(outcomes):
    failed = [o for o in outcomes if o.status == "failed"]
    assert not failed, "documented examples that break:\n" + docs.report(outcomes)


def help_examples_in_order():
    from perscli.cli.main import cli

    names = [n for n in HELP_ORDER if n in cli.commands] + sorted(set(cli.commands) - set(HELP_ORDER))
    return [ex for name in names for ex in docs.help_examples(cli.commands[name])]


def test_every_command_documents_examples():
    from perscli.cli.main import cli

    lacking = [name for name, cmd in cli.commands.items() if not docs.help_examples(cmd)]
    assert not lacking, f"commands whose --help has no Examples block: {lacking}"


def test_the_harness_fails_a_broken_example_and_a_clobbered_output(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("Intro\n\n    perscli budget -o b.fits\n    perscli budget --no-such-option -o c.fits\n\n"
                      "```sh\nperscli budget --theta-range 1 10 \\\n    -o b.fits\n```\n")
    examples = docs.readme_examples(readme)
    assert [e.command for e in examples] == ["perscli budget -o b.fits", "perscli budget --no-such-option -o c.fits",
                                             "perscli budget --theta-range 1 10 -o b.fits"]
    folder = tmp_path / "run"
    docs.prepare_folder(folder, SHARED_DATA, docs.script_dir())
    outcomes = docs.run_examples(examples, folder, shared=SHARED_DATA)
    assert [o.status for o in outcomes] == ["ok", "failed", "failed"]
    assert "exit 2" in outcomes[1].reason and "distinct" in outcomes[2].reason
    with pytest.raises(AssertionError, match="no-such-option"):
        _check(outcomes)


@pytest.mark.parametrize("source", [pytest.param("readme", marks=pytest.mark.slow), "help"])
def test_documented_examples_run(tmp_path, source):
    """README's examples in one folder (a clone as it is: it runs the small study, so it is slow), the --help
    examples of every command in another (the sample files beside them), each in order."""
    examples = docs.readme_examples() if source == "readme" else help_examples_in_order()
    assert len(examples) >= 30
    folder = tmp_path / "clone"
    docs.prepare_folder(folder, SHARED_DATA, docs.script_dir(), samples_at_top=source == "help")
    outcomes = docs.run_examples(examples, folder, shared=SHARED_DATA)
    print(docs.report(outcomes))
    _check(outcomes)


def test_examples_needing_absent_shared_inputs_are_skipped_with_what_they_make(tmp_path):
    """Without ../shared: an example naming a shared file, or a repository file that names one, is skipped,
    and so is every later example reading what it would have made (a file inside its output folder too)."""
    absent = tmp_path / "no-shared" / "data"
    examples = [docs.Example("t", "perscli study examples/small.yaml -o small_study"),
                docs.Example("t", "perscli study --preset paper -o plan --dry-run --cost-from small_study/cost.json"),
                docs.Example("t", "perscli pointings --schedule Roman_WAS_obseq_11_1_23.fits --before 3 --n 2 -o p.fits"),
                docs.Example("t", "perscli catalog --pointings p.fits --sca 7 -o c.fits")]
    folder = tmp_path / "clone"
    docs.prepare_folder(folder, absent, docs.script_dir())
    outcomes = docs.run_examples(examples, folder, shared=absent)
    assert [o.status for o in outcomes] == ["skipped"] * 4
    assert "small_study/cost.json" in outcomes[1].reason or "Roman_WAS" in outcomes[1].reason
    assert "p.fits, made by a skipped example" in outcomes[3].reason
