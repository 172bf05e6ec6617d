"""Robot-id claims (tagswarm/deploy/claims.py, claim.py) and the lockstep participants that
follow the robot count (``agent/*``).  No session is opened: the containers test
(tests/e2e/test_compose_containers.py) and tests/e2e/test_compose.py run them."""

from __future__ import annotations

from pathlib import Path

import pytest

from tagswarm.deploy import acl, claims
from tagswarm.protocol.scenario import load_scenario
from tagswarm.runtime.config import ConfigError


def test_ids_go_lowest_first_each_once_then_every_claim_is_refused() -> None:
    passwords = {acl.agent_user(r): f"pw{r}" for r in range(3)}
    book = claims.ClaimBook((0, 1, 2), passwords)
    granted = [book.claim() for _ in range(3)]
    assert [(g.robot_id, g.user, g.password, g.robots) for g in granted] == [
        (0, "agent0", "pw0", 3), (1, "agent1", "pw1", 3), (2, "agent2", "pw2", 3)]
    assert all(g.granted for g in granted)
    refused = book.claim()
    assert not refused.granted and refused.robot_id == -1 and refused.password == "" and refused.user == ""
    assert refused.reason == "every robot id is taken (3 robots)"
    assert book.taken == [0, 1, 2] and book.refused == 1


def test_a_robot_without_a_password_is_a_one_line_error() -> None:
    with pytest.raises(ConfigError, match=r"no password for agent2, agent3 \(run tagswarm router --make-secrets DIR "
                                          r"--robots 4\)"):
        claims.ClaimBook((0, 1, 2, 3), {"agent0": "a", "agent1": "b"})


def test_replies_round_trip_and_garbage_is_no_reply() -> None:
    reply = claims.ClaimReply(seq=0, stamp_ns=0, robot_id=4, robots=6, user="agent4", password="s3cret")
    assert claims.decode(claims.encode(reply)) == reply
    assert claims.decode(b"FORGED") is None
    assert claims.decode(claims.encode(reply)[:-3]) is None


def test_the_agents_file_written_by_make_secrets_feeds_the_book(tmp_path: Path) -> None:
    acl.make_secrets(tmp_path, acl.users(range(4)))
    passwords = claims.read_passwords(tmp_path / acl.AGENTS_FILE)
    assert sorted(passwords) == ["agent0", "agent1", "agent2", "agent3"]
    for user, password in passwords.items():
        assert (tmp_path / f"{user}{acl.PASSWORD_SUFFIX}").read_text().strip() == password
    assert claims.ClaimBook(range(4), passwords).claim().password == passwords["agent0"]
    bad = tmp_path / "bad.txt"
    bad.write_text("agent0:x\nno-colon\n")
    with pytest.raises(ConfigError, match="line 2 is not user:password"):
        claims.read_passwords(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        claims.read_passwords(tmp_path / "missing.txt")


@pytest.mark.parametrize("argv,env,message", [
    ([], {}, "give the command to run after --"),
    (["--"], {}, "give the command to run after --"),
    (["--timeout", "0", "--", "true"], {}, "--timeout must be a positive number"),
    (["--", "true"], {"TAGSWARM_ROBOT_ID": "1"}, "TAGSWARM_ROBOT_ID is already set"),
])
def test_claim_usage_errors_exit_2_with_one_line(argv: list[str], env: dict[str, str], message: str,
                                                 capsys: pytest.CaptureFixture[str],
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    from tagswarm import cli

    for key, value in env.items():
        monkeypatch.setenv(key, value)
    assert cli.main(["claim", *argv]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and err.startswith("tagswarm claim: error: ") and message in err, err


def test_the_agents_wildcard_expands_to_every_robot_of_the_scenario() -> None:
    for count in (1, 4, 6):
        s = load_scenario("paper", [f"robots.count={count}", 'clock.participants=["agent/*","server/0"]'])
        assert s.clock.participants == (*(f"agent/{r}" for r in range(count)), "server/0")
    # an explicit list is left alone, and a name given twice is declared once
    s = load_scenario("paper", ['clock.participants=["agent/1","agent/*"]'])
    assert s.clock.participants == ("agent/1", "agent/0", "agent/2", "agent/3")
    assert load_scenario("paper").clock.participants == ()
