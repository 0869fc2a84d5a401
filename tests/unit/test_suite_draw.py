"""The short suite's draw of each family's cases (aft_ftm.suite): seeded, every family runs, every
member is drawn over seeds, the full suite runs all, bad settings refused by name."""
import collections

import pytest

from aft_ftm import suite


MEMBERS = ['a', 'b', 'c', 'd', 'e']


def test_a_seed_draws_keep_members_the_same_every_time_whatever_their_order():
    first = suite.drawn('f', MEMBERS, 2, 41)
    assert len(first) == 2 and first <= set(MEMBERS)
    assert suite.drawn('f', list(reversed(MEMBERS)), 2, 41) == first


def test_over_seeds_every_member_runs_and_about_as_often():
    counts = collections.Counter()
    for seed in range(2000):
        counts.update(suite.drawn('f', MEMBERS, 2, seed))
    assert set(counts) == set(MEMBERS)
    assert all(650 < n < 950 for n in counts.values()), counts   # 800 expected each


def test_families_draw_independently():
    together = sum(suite.drawn('f', MEMBERS, 1, s) == suite.drawn('g', MEMBERS, 1, s) for s in range(500))
    assert together < 200   # 100 expected if independent; the same draw for both would give 500


def test_the_full_suite_or_a_keep_covering_the_family_runs_every_member():
    assert suite.drawn('f', MEMBERS, 2, 7, suite.FULL) == set(MEMBERS)
    assert suite.drawn('f', MEMBERS, 5, 7) == set(MEMBERS)
    assert suite.drawn('f', MEMBERS, 9, 7) == set(MEMBERS)


def test_bad_settings_are_refused_naming_them():
    with pytest.raises(ValueError, match='AFT_SUITE=.quick.'):
        suite.suite({'AFT_SUITE': 'quick'})
    with pytest.raises(ValueError, match='AFT_SUITE_SEED=.x1.'):
        suite.seed({'AFT_SUITE_SEED': 'x1'})
    with pytest.raises(ValueError, match='family f: keep'):
        suite.drawn('f', MEMBERS, 0, 1)
    families = suite.Families()
    families.add('f', 1, 'a')
    with pytest.raises(ValueError, match='family f declared with keep 1 and 2'):
        families.add('f', 2, 'b')


def test_a_seed_made_from_the_time_is_put_in_the_environment_for_the_processes_started_after():
    environ = {}
    value = suite.seed(environ)
    assert environ['AFT_SUITE_SEED'] == str(value)
    assert suite.seed(environ) == value


def test_families_say_why_a_member_is_skipped_and_never_skip_one_of_no_family():
    families = suite.Families()
    for member in MEMBERS:
        families.add('f', 2, member)
    environ = {'AFT_SUITE_SEED': '12'}
    reasons = {m: families.skip_reason(m, environ) for m in MEMBERS}
    run = [m for m, why in reasons.items() if why is None]
    assert sorted(run) == sorted(suite.drawn('f', MEMBERS, 2, 12))
    skipped = [why for why in reasons.values() if why]
    assert len(skipped) == 3 and all('family f runs 2 of its 5' in why and 'AFT_SUITE_SEED=12' in why and
                                     'AFT_SUITE=full' in why for why in skipped)
    assert families.skip_reason('other', environ) is None
    assert all(families.skip_reason(m, dict(environ, AFT_SUITE='full')) is None for m in MEMBERS)


def test_a_case_not_drawn_is_said_on_the_output_and_in_the_results_folder(tmp_path, capsys):
    suite.say_not_drawn('TestX.test_y', 'why', {'AFT_RESULTS_DIR': str(tmp_path)})
    suite.say_not_drawn('TestX.test_z', 'why', {'AFT_RESULTS_DIR': str(tmp_path)})
    assert 'AFT_SUITE_SKIPPED TestX.test_y: why' in capsys.readouterr().out
    assert (tmp_path / suite.NOT_DRAWN_FILE).read_text().split() == ['TestX.test_y', 'TestX.test_z']
