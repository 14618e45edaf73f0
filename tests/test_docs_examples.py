"""Every documented example runs as written from the root of a clone: README.md's, and every command's --help
Examples (which the man pages are made of).

README's examples run in order in one folder standing for a clone; each
command's --help examples run in order in a folder of their own, also a
clone (sample_data/, examples/; nothing else at the top): a page's examples
make what they need first, or read what the clone holds.  Both folders get
(links to) the real inputs of ../shared/data by name, as a user who
downloaded them would have them; an example naming a shared input that is
absent is skipped, every other one must exit 0 and write outputs no earlier
example of its folder wrote.  The examples that run whole studies, plan the
paper's or run diagnose take tens of seconds to minutes each: the slow tests
run them, the fast ones every other example.
"""


import pytest

from conftest import SHARED_DATA
import docexamples as docs
from fits_factory import commands

HELP_ORDER = ("pointings", "catalog", "render", "apply-persistence", "measure", "correlate", "budget", "diagnose",
              "study", "man", "completion")


def _check(outcomes):
    failed = [o for o in outcomes if o.status == "failed"]
    assert not failed, "documented examples that break:\n" + docs.report(outcomes)


def help_examples_of(name):
    return docs.help_examples(commands()[name])


def _command_names():
    names = commands()
    return [n for n in HELP_ORDER if n in names] + sorted(set(names) - set(HELP_ORDER))


def test_every_command_documents_examples():
    lacking = [name for name, cmd in commands().items() if not docs.help_examples(cmd)]
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


def _run(examples, tmp_path, *, expensive):
    folder = tmp_path / "clone"
    docs.prepare_folder(folder, SHARED_DATA, docs.script_dir(), samples_at_top=False)
    outcomes = docs.run_examples(examples, folder, shared=SHARED_DATA, expensive=expensive)
    print(docs.report(outcomes))
    _check(outcomes)
    return outcomes


def test_the_help_examples_run_from_a_clone(tmp_path):
    """Each command's --help examples, in order, in a clone of their own: but the expensive ones (docs.EXPENSIVE).

    Two commands' examples at a time: each is a chain of short processes (interpreter start, GalSim import), one
    core's work, and the suite would otherwise leave the second core of a 2-core machine idle for minutes.
    """
    from concurrent.futures import ThreadPoolExecutor

    def one(name):
        folder = tmp_path / name
        docs.prepare_folder(folder, SHARED_DATA, docs.script_dir(), samples_at_top=False)
        return name, docs.run_examples(help_examples_of(name), folder, shared=SHARED_DATA, expensive=False)

    with ThreadPoolExecutor(max_workers=2) as pool:
        results = dict(pool.map(one, _command_names()))
    print("\n".join(docs.report(outcomes) for outcomes in results.values()))
    _check([o for outcomes in results.values() for o in outcomes])
    idle = [name for name, outcomes in results.items() if not any(o.status == "ok" for o in outcomes)]
    assert not idle, f"commands none of whose --help examples ran: {idle}"


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n in _command_names()
                                  if any(docs.is_expensive(e.command) for e in help_examples_of(n))])
def test_the_help_examples_that_run_studies(tmp_path, name):
    _run(help_examples_of(name), tmp_path, expensive=True)


@pytest.mark.slow
def test_the_readme_examples_run_from_a_clone(tmp_path):
    """README's examples in order in one clone (it runs the small study and plans the paper's: slow)."""
    examples = docs.readme_examples()
    assert len(examples) >= 30
    _run(examples, tmp_path, expensive=True)


def test_the_fast_help_examples_run_no_study():
    """What the fast suite runs of the help examples: no whole study, no plan of the paper's (minutes each)."""
    cheap = [e.command for n in _command_names() for e in help_examples_of(n) if not docs.is_expensive(e.command)]
    assert any("study examples/small.yaml" in c and "--dry-run" in c for c in cheap)
    assert not [c for c in cheap if c.startswith("perscli study") and "--dry-run" not in c]
    assert not [c for c in cheap if "--preset paper" in c]


def test_examples_needing_absent_shared_inputs_are_skipped_with_what_they_make(tmp_path):
    """Without ../shared: an example naming a shared file is skipped, and so is every later example reading what
    it would have made (a file inside its output folder too); the bundled schedule needs nothing."""
    absent = tmp_path / "no-shared" / "data"
    examples = [docs.Example("t", "perscli catalog --ra 10 --dec -44 --gaia 145649.fits -o g.fits"),
                docs.Example("t", "perscli pointings plan --ra 10 --dec -44 --n 2 --sca 7 -o p.fits"),
                docs.Example("t", "perscli catalog --pointings p.fits --sca 7 --margin 5 --gaia 145650.fits -o c.fits"),
                docs.Example("t", "perscli measure x.fits --catalog g.fits -o m.fits"),
                docs.Example("t", "perscli study examples/small.yaml -o small_study"),
                docs.Example("t", "perscli study --preset paper -o plan --dry-run --cost-from small_study/cost.json"),
                docs.Example("t", "perscli pointings before --row 3 --n 2 -o b.fits")]
    folder = tmp_path / "clone"
    docs.prepare_folder(folder, absent, docs.script_dir(), samples_at_top=False)
    outcomes = docs.run_examples(examples, folder, shared=absent, expensive=False)
    assert [o.status for o in outcomes] == ["skipped", "ok", "skipped", "skipped", "skipped", "skipped", "ok"], \
        docs.report(outcomes)
    assert "145649.fits" in outcomes[0].reason and "g.fits, made by a skipped example" in outcomes[3].reason
    assert "whole study" in outcomes[4].reason and "slow tests" in outcomes[4].reason
