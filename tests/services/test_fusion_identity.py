"""Per-robot identity on the fusion server: per-agent tokens from a hashed token file, the fleet
token's team-wide mode, writes only to the caller's own agent id (PERMISSION_DENIED otherwise, with a
log line), revocation (token file change, SIGHUP), reads for every team member, the agent side sending
its own token, and the ``gausslite tokens`` command. Real in-process gRPC servers on ephemeral
loopback ports, as in tests/services/test_fusion_server.py (docs/security.md)."""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
import time

import grpc
import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.cli import main as cli_main
from gausslite.datasets.base import Frame
from gausslite.wire.codec import GaussianArrays, encode_subset
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common import auth
from gausslite_services.common.server import ServerOptions, run_until_signalled
from gausslite_services.fusion_server.client import FusionClient, client_credentials_from_env
from gausslite_services.fusion_server.server import serve

H, W = 24, 32
INTR = Intrinsics(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, W, H)
DENIED = grpc.StatusCode.PERMISSION_DENIED
UNAUTH = grpc.StatusCode.UNAUTHENTICATED


def rand_subset(n: int, offset: float, seed: int) -> GaussianArrays:
    r = np.random.default_rng(seed)
    return GaussianArrays(means=r.uniform(0, 1, (n, 3)) + offset, quats=r.normal(size=(n, 4)),
                          log_scales=r.uniform(-5, -3, (n, 3)), opacity_logits=r.normal(size=n),
                          colors=r.uniform(0, 1, (n, 3)), kappa=r.integers(0, 100, n), active=r.random(n) < 0.5)


def frame(i: int) -> Frame:
    r = np.random.default_rng(i)
    return Frame(i, i / 30.0, r.uniform(0, 255, (H, W, 3)).astype(np.uint8), np.full((H, W), 1.5, np.float32),
                 np.eye(4), INTR)


def code_of(fn):
    with pytest.raises(grpc.RpcError) as ei:
        fn()
    return ei.value.code(), ei.value.details()


@pytest.fixture()
def tokens(tmp_path):
    """A token file with robot-a, robot-b and a viewer that never writes; returns (path, {id: token})."""
    path = tmp_path / "fusion_tokens.yaml"
    return path, {a: auth.issue_token(path, a) for a in ("robot-a", "robot-b", "viewer")}


def start(tmp_path, **kw):
    return serve(ServerOptions(port=0, max_workers=8, grace_s=0.5, **kw), data_dir=str(tmp_path / "data"))


def client(srv, token=None) -> FusionClient:
    return FusionClient(f"127.0.0.1:{srv.port}", token=token, timeout_s=10)


def stub(srv, token):
    ch = grpc.insecure_channel(f"127.0.0.1:{srv.port}")
    return ch, fusion_pb2_grpc.FusionStub(ch), (("authorization", f"Bearer {token}"),)


def upload_raw(st, md, agent, version, chunks, indices):
    msgs = [fusion_pb2.UploadSubsetRequest(header=fusion_pb2.UploadHeader(
        agent_id=agent, map_version=version, n_chunks=len(chunks)))]
    msgs += [fusion_pb2.UploadSubsetRequest(chunk=chunks[i]) for i in indices]
    return st.UploadSubset(iter(msgs), timeout=10, metadata=md)


# --------------------------------------------------------------------------------------------- writes


def test_a_robot_writes_only_its_own_agent_id(tmp_path, tokens, caplog):
    path, tok = tokens
    srv = start(tmp_path, agent_tokens_file=str(path))
    try:
        with client(srv, tok["robot-a"]) as a, client(srv, tok["robot-b"]) as b:
            # as itself: open, push a subset, push keyframes, re-open (resume) the session
            assert a.open_session("robot-a", "find the cup", INTR).created
            assert a.upload_subset("robot-a", 1, rand_subset(500, 0.0, 1), full_map_gaussians=5000,
                                   chunk_gaussians=200).complete
            assert a.upload_keyframes("robot-a", [frame(1), frame(2)]) == 2
            again = a.open_session("robot-a", "find the cup", INTR)
            assert not again.created and again.latest_map_version == 1

            # robot-b opens its session and leaves an upload half done (to be resumed later)
            b.open_session("robot-b", "find the desk", INTR)
            chunks_b = encode_subset(rand_subset(600, 0.5, 2), "robot-b", 3, chunk_gaussians=200)
            ch, st, md_b = stub(srv, tok["robot-b"])
            with ch:
                assert upload_raw(st, md_b, "robot-b", 3, chunks_b, [0]).missing == [1, 2]
            before = b.upload_status("robot-b", 3)

            caplog.set_level(logging.WARNING)
            # robot-a may not open, resume, overwrite or feed robot-b's session
            code, msg = code_of(lambda: a.open_session("robot-b", "hijack", INTR))
            assert code == DENIED and "robot-a" in msg and "robot-b" in msg
            ch, st, md_a = stub(srv, tok["robot-a"])
            with ch:
                # resume robot-b's half-done upload with robot-b's own chunks
                assert code_of(lambda: upload_raw(st, md_a, "robot-b", 3, chunks_b, [1, 2]))[0] == DENIED
                # a newer version would supersede (delete) robot-b's subset
                newer = encode_subset(rand_subset(50, 0.5, 3), "robot-b", 9, chunk_gaussians=200)
                assert code_of(lambda: upload_raw(st, md_a, "robot-b", 9, newer, [0]))[0] == DENIED
            assert code_of(lambda: a.upload_keyframes("robot-b", [frame(5)]))[0] == DENIED
            # a stream that switches to another agent is cut at the first foreign keyframe
            ch, st, md_a = stub(srv, tok["robot-a"])
            with ch:
                from gausslite_services.fusion_server.client import keyframe_to_proto

                msgs = [keyframe_to_proto("robot-a", frame(7)), keyframe_to_proto("robot-b", frame(8))]
                assert code_of(lambda: st.UploadKeyframes(iter(msgs), timeout=10, metadata=md_a))[0] == DENIED
            # nothing of robot-b changed
            after = b.upload_status("robot-b", 3)
            assert (list(after.stored), after.complete) == (list(before.stored), before.complete) == ([0], False)
            stats = b.stats()["agents"]
            assert stats["robot-b"]["keyframes"] == 0 and stats["robot-b"]["task_text"] == "find the desk"
            assert "robot-b" not in {p["agent_id"] for p in b.keyframe_poses()}
            # every refusal was logged with the method, the caller and the agent
            denied = [r.getMessage() for r in caplog.records if "PERMISSION_DENIED" in r.getMessage()]
            assert any(m.startswith("rejected OpenSession from ") and "agent 'robot-a' (agent-token)" in m
                       and "'robot-b'" in m for m in denied)
            assert sum("rejected UploadSubset" in m for m in denied) == 2
            assert sum("rejected UploadKeyframes" in m for m in denied) == 2

            # robot-b resumes its own upload
            ch, st, md_b = stub(srv, tok["robot-b"])
            with ch:
                assert upload_raw(st, md_b, "robot-b", 3, chunks_b, [1, 2]).complete
    finally:
        srv.stop(0.5)


def test_reads_and_fuse_are_open_to_every_team_member(tmp_path, tokens):
    path, tok = tokens
    srv = start(tmp_path, agent_tokens_file=str(path), token="fleet-wide-secret")
    try:
        with client(srv, tok["robot-a"]) as a:
            a.open_session("robot-a", "find the cup", INTR)
            a.upload_subset("robot-a", 1, rand_subset(400, 0.0, 1), full_map_gaussians=4000)
            a.upload_keyframes("robot-a", [frame(1)])
        # a team member that never writes (its own id is "viewer"), robot-b and the fleet token: all read
        for token in (tok["viewer"], tok["robot-b"], "fleet-wide-secret"):
            with client(srv, token) as c:
                assert c.stats()["agents"]["robot-a"]["gaussians_received"] == 400
                assert c.upload_status("robot-a", 1).complete
                assert [p["agent_id"] for p in c.keyframe_poses("robot-a")] == ["robot-a"]
                r = c.fuse("concat")
                assert r.kept == {"robot-a": 400}
                assert len(c.download_fused(r.fused_version)) == 400
        # next to per-agent tokens the fleet token writes nobody's data ...
        with client(srv, "fleet-wide-secret") as fleet:
            code, msg = code_of(lambda: fleet.open_session("robot-a", "x", INTR))
            assert code == DENIED and "team member (fleet-token)" in msg
            assert code_of(lambda: fleet.open_session("anyone", "x", INTR))[0] == DENIED
        # ... and no credential, a wrong one or a malformed header reads nothing
        for token in (None, "not-a-token"):
            with client(srv, token) as c:
                assert code_of(c.stats)[0] == UNAUTH
        ch, st, _ = stub(srv, "x")
        with ch:
            for md in ((("authorization", tok["robot-a"]),), (("authorization", "Basic abc"),),
                       (("authorization", f"Bearer {tok['robot-a']}"), ("authorization", f"Bearer {tok['robot-b']}"))):
                assert code_of(lambda: st.GetStats(fusion_pb2.StatsRequest(), timeout=5, metadata=md))[0] == UNAUTH
    finally:
        srv.stop(0.5)


def test_fleet_token_alone_is_the_team_wide_mode(tmp_path, tokens):
    srv = start(tmp_path, token="fleet-wide-secret")
    try:
        with client(srv, "fleet-wide-secret") as c:
            c.open_session("robot-a", "a", INTR)
            c.open_session("robot-b", "b", INTR)  # any agent id
            assert c.upload_subset("robot-b", 1, rand_subset(100, 0.0, 1), full_map_gaussians=100).complete
        with client(srv, "wrong") as c:
            assert code_of(c.stats)[0] == UNAUTH
    finally:
        srv.stop(0.5)
    # migration: the fleet token may keep write access next to per-agent tokens when asked to
    path, tok = tokens
    srv = start(tmp_path, token="fleet-wide-secret", agent_tokens_file=str(path), fleet_token_writes=True)
    try:
        with client(srv, "fleet-wide-secret") as c:
            c.open_session("robot-a", "a", INTR)
        with client(srv, tok["robot-b"]) as b:
            assert code_of(lambda: b.open_session("robot-a", "a", INTR))[0] == DENIED
    finally:
        srv.stop(0.5)


# --------------------------------------------------------------------------------------------- revocation


def test_a_revoked_token_is_refused(tmp_path, tokens, caplog):
    path, tok = tokens
    srv = start(tmp_path, agent_tokens_file=str(path))
    try:
        with client(srv, tok["robot-a"]) as a, client(srv, tok["robot-b"]) as b:
            a.open_session("robot-a", "find the cup", INTR)
            caplog.set_level(logging.INFO)
            assert auth.revoke_token(path, "robot-a")  # the file changes: re-read before the next call
            for call in (a.stats, lambda: a.open_session("robot-a", "find the cup", INTR)):
                code, msg = code_of(call)
                assert code == UNAUTH and "invalid or revoked" in msg
            assert any("revoked robot-a" in r.getMessage() for r in caplog.records)
            assert any("rejected call /gausslite.v1.Fusion/GetStats" in r.getMessage() and "UNAUTHENTICATED"
                       in r.getMessage() for r in caplog.records)
            b.open_session("robot-b", "find the desk", INTR)  # the others are unaffected
            # a new token for robot-a works, the revoked one stays refused
            new = auth.issue_token(path, "robot-a")
            with client(srv, new) as a2:
                assert not a2.open_session("robot-a", "find the cup", INTR).created
            assert code_of(a.stats)[0] == UNAUTH
            # rotation: old and new token both work until the old one is revoked
            newer = auth.issue_token(path, "robot-a", keep_old=True)
            with client(srv, new) as old_c, client(srv, newer) as new_c:
                old_c.stats()
                new_c.stats()
                assert auth.revoke_token(path, "robot-a", keep_newest=True)
                assert code_of(old_c.stats)[0] == UNAUTH
                new_c.stats()
    finally:
        srv.stop(0.5)


def test_a_broken_token_file_fails_closed_until_fixed(tmp_path, tokens):
    path, tok = tokens
    srv = start(tmp_path, agent_tokens_file=str(path), token="fleet-wide-secret")
    try:
        good = path.read_text()
        with client(srv, tok["robot-a"]) as a, client(srv, "fleet-wide-secret") as fleet:
            a.stats()
            path.write_text("agents: [this is: not a mapping")
            assert code_of(a.stats)[0] == UNAUTH
            fleet.stats()  # the fleet token does not depend on the file
            path.write_text(good)
            a.stats()
    finally:
        srv.stop(0.5)
    # a broken file at start-up stops the server from starting, with a precise error
    path.write_text(json.dumps({"agents": {"robot a": "sha256:" + "0" * 64}}))
    with pytest.raises(ValueError, match="invalid agent id 'robot a'"):
        start(tmp_path, agent_tokens_file=str(path))


def test_sighup_reloads_the_token_file(tmp_path, tokens):
    """SIGHUP re-reads the file even when an in-place edit kept its mtime, size and inode."""
    path, tok = tokens
    srv = start(tmp_path, agent_tokens_file=str(path))
    stop = threading.Event()
    outcome = {}

    def placeholder(*_):  # never the default action (terminate) while the test runs
        pass

    previous = signal.signal(signal.SIGHUP, placeholder)

    def driver():
        try:
            with client(srv, tok["robot-a"]) as a:
                a.stats()
                st = os.stat(path)
                text = path.read_text()
                old = auth.read_token_file(path)["robot-a"][0]
                new = text.replace(old, auth.hash_token(auth.new_token()))  # same length
                assert len(new) == len(text) and new != text
                with open(path, "r+", encoding="utf-8") as f:  # in place: same inode
                    f.write(new)
                os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
                assert (os.stat(path).st_mtime_ns, os.stat(path).st_ino) == (st.st_mtime_ns, st.st_ino)
                outcome["before_hup"] = a.stats() is not None  # unchanged signature: not re-read
                deadline = time.monotonic() + 10
                while signal.getsignal(signal.SIGHUP) is placeholder:
                    assert time.monotonic() < deadline
                    time.sleep(0.05)
                os.kill(os.getpid(), signal.SIGHUP)
                while time.monotonic() < deadline:
                    try:
                        a.stats()
                    except grpc.RpcError as e:
                        outcome["after_hup"] = e.code()
                        break
                    time.sleep(0.1)
        except BaseException as e:  # noqa: BLE001 - reported by the main thread
            outcome["error"] = e
        finally:
            stop.set()

    t = threading.Thread(target=driver, daemon=True)
    try:
        t.start()
        run_until_signalled(srv, stop)  # the main thread: installs the SIGHUP handler, stops the server at the end
        t.join(10)
    finally:
        signal.signal(signal.SIGHUP, previous)
        srv.stop(0.5)
    assert "error" not in outcome, outcome.get("error")
    assert outcome == {"before_hup": True, "after_hup": UNAUTH}


# --------------------------------------------------------------------------------------------- agent side


def test_the_agent_sends_its_own_token(tmp_path, tokens):
    from gausslite_services.agent.server import AgentServicer, settings_from_env

    path, tok = tokens
    secret = tmp_path / "robot-a.token"
    auth.write_secret(secret, tok["robot-a"])
    srv = start(tmp_path, agent_tokens_file=str(path), token="fleet-wide-secret")
    try:
        env = {"GAUSSLITE_AGENT_ID": "robot-a", "GAUSSLITE_FUSION_TOKEN_FILE": str(secret)}
        settings = settings_from_env(None, env=env, token="fleet-wide-secret")  # the fleet token: parser
        assert settings.fusion_token_file == str(secret)
        servicer = AgentServicer(settings)
        fc = servicer._fusion_client(f"127.0.0.1:{srv.port}")
        try:
            assert fc.open_session("robot-a", "find the cup", INTR).agent_id == "robot-a"
            assert code_of(lambda: fc.open_session("robot-b", "x", INTR))[0] == DENIED
        finally:
            fc.close()
        # a token file gone since start-up: the mission cannot connect, with a precise error
        from gausslite.mission import MissionError

        moved = tmp_path / "moved.token"
        secret.rename(moved)
        with pytest.raises(MissionError, match="fusion credentials unusable"):
            servicer._fusion_client(f"127.0.0.1:{srv.port}")
        moved.rename(secret)
        # the same from the environment helper used by the viewer and the report job
        creds = client_credentials_from_env({"GAUSSLITE_FUSION_TOKEN_FILE": str(secret), "GAUSSLITE_TOKEN": "fleet"})
        assert creds == {"token": tok["robot-a"], "root_cert": None, "client_cert": None, "client_key": None}
        assert client_credentials_from_env({"GAUSSLITE_TOKEN": "fleet"})["token"] == "fleet"
        # a missing or empty token file fails at start-up with the file's name
        (tmp_path / "empty.token").write_text("\n")
        with pytest.raises(ValueError, match="empty.token is empty"):
            settings_from_env(None, env={**env, "GAUSSLITE_FUSION_TOKEN_FILE": str(tmp_path / "empty.token")})
        with pytest.raises(FileNotFoundError):
            settings_from_env(None, env={**env, "GAUSSLITE_FUSION_TOKEN_FILE": str(tmp_path / "nope")})
    finally:
        srv.stop(0.5)


# --------------------------------------------------------------------------------------------- token file, CLI


def test_token_hashes_and_file_validation(tmp_path):
    t = auth.new_token()
    sha = auth.hash_token(t)
    pb = auth.hash_token(t, "pbkdf2", iterations=10_000)
    assert sha.startswith("sha256:") and pb.startswith("pbkdf2_sha256$10000$")
    assert auth.verify_token(t, sha) and auth.verify_token(t, pb)
    assert not auth.verify_token(t + "x", sha) and not auth.verify_token(t + "x", pb)
    assert t not in sha and t not in pb
    for bad in ("", " lead", "trail ", "tab\t", "ü"):
        with pytest.raises(ValueError):
            auth.hash_token(bad)
    with pytest.raises(ValueError):
        auth.verify_token(t, "md5:abc")
    # a file of pbkdf2 records identifies its agents too
    path = tmp_path / "t.json"
    other = auth.new_token()
    path.write_text(json.dumps({"agents": {"robot-a": pb, "robot-b": [auth.hash_token(other)]}}))
    store = auth.AgentTokens(path)
    assert store.identify(t) == "robot-a" and store.identify(t) == "robot-a" and store.identify("nope") is None
    assert store.identify(other) == "robot-b" and store.agents() == ["robot-a", "robot-b"]
    for doc, err in [({"robots": {}}, "one key 'agents'"), ({"agents": ["robot-a"]}, "must map agent ids"),
                     ({"agents": {"robot-a": "sha256:xyz"}}, "malformed token hash"),
                     ({"agents": {"robot-a": []}}, "non-empty list"),
                     ({"agents": {"a": sha, "b": sha}}, "share one token"),
                     ({"agents": {"x" * 65: sha}}, "invalid agent id")]:
        with pytest.raises(ValueError, match=err):
            auth.parse_token_records(doc)
    assert auth.parse_token_records({"agents": {}}) == {} and auth.parse_token_records({}) == {}
    # metadata parsing
    assert auth.bearer_token(None) is None and auth.bearer_token([("x", "y")]) is None
    assert auth.bearer_token([("authorization", "Bearer a b")]) == "a b"
    for md in ([("authorization", "Bearer ")], [("authorization", "bearer x")], [("Authorization", "x")]):
        with pytest.raises(auth.AuthError) as ei:
            auth.bearer_token(md)
        assert ei.value.code == UNAUTH


def test_tokens_command(tmp_path, capsys):
    d = tmp_path / "secrets"
    assert cli_main(["tokens", "provision", "--dir", str(d), "agent_a", "agent_b"]) == 0
    tok_a = (d / "agent_a.token").read_text().strip()
    assert oct((d / "agent_a.token").stat().st_mode & 0o777) == "0o600"
    recs = auth.read_token_file(d / "fusion_tokens.json")
    assert set(recs) == {"agent_a", "agent_b"} and tok_a not in (d / "fusion_tokens.json").read_text()
    assert auth.AgentTokens(d / "fusion_tokens.json").identify(tok_a) == "agent_a"
    # provisioning again keeps existing tokens; --force replaces them
    assert cli_main(["tokens", "provision", "--dir", str(d), "agent_a"]) == 0
    assert (d / "agent_a.token").read_text().strip() == tok_a
    assert cli_main(["tokens", "provision", "--dir", str(d), "--force", "agent_a"]) == 0
    assert (d / "agent_a.token").read_text().strip() != tok_a
    capsys.readouterr()
    assert cli_main(["tokens", "issue", "robot-9", "--tokens-file", str(d / "fusion_tokens.json")]) == 0
    tok9 = capsys.readouterr().out.strip()
    assert auth.AgentTokens(d / "fusion_tokens.json").identify(tok9) == "robot-9"
    assert cli_main(["tokens", "hash", "--token", tok9]) == 0
    assert capsys.readouterr().out.strip() == auth.hash_token(tok9)
    assert cli_main(["tokens", "revoke", "robot-9", "--tokens-file", str(d / "fusion_tokens.json")]) == 0
    assert cli_main(["tokens", "revoke", "robot-9", "--tokens-file", str(d / "fusion_tokens.json")]) == 1
    assert cli_main(["tokens", "issue", "bad id", "--tokens-file", str(d / "fusion_tokens.json")]) == 2
    assert "invalid agent id" in capsys.readouterr().err


def test_serve_cli_credentials_options(tmp_path, tokens):
    from gausslite.cli import build_parser
    from gausslite_services.cli.cmd_serve import resolve_options

    path, _ = tokens
    args = build_parser().parse_args(["serve", "fusion", "--agent-tokens", str(path), "--tls-client-ca", "ca.pem"])
    opts, _ = resolve_options(args, env={})
    assert (opts.agent_tokens_file, opts.tls_client_ca, opts.fleet_token_writes) == (str(path), "ca.pem", None)
    env = {"GAUSSLITE_AGENT_TOKENS_FILE": str(path), "GAUSSLITE_FLEET_TOKEN_WRITES": "1"}
    opts, _ = resolve_options(build_parser().parse_args(["serve", "fusion"]), env=env)
    assert opts.agent_tokens_file == str(path) and opts.fleet_token_writes is True
    # the other services ignore the fusion token file from the environment and refuse the flag
    assert resolve_options(build_parser().parse_args(["serve", "parser"]), env=env)[0].agent_tokens_file is None
    with pytest.raises(ValueError, match="fusion server only"):
        resolve_options(build_parser().parse_args(["serve", "agent", "--agent-tokens", str(path)]), env={})
    # the fusion module's own CLI: a broken token file is a precise start-up error (exit 2)
    from gausslite_services.fusion_server.server import main as fusion_main

    bad = tmp_path / "bad.json"
    bad.write_text("{")
    assert fusion_main(["--port", "0", "--data-dir", str(tmp_path / "d"), "--agent-tokens", str(bad)]) == 2


def test_wrong_tokens_from_one_peer_cannot_starve_the_robots(tmp_path):
    """A peer over its budget of failed authentications gets only the cheap checks: its unknown tokens are refused
    without a key derivation (PBKDF2, about 65 ms per record), while a robot's token verified before, from the same
    address, still works."""
    from gausslite_services.common.server import FailureLimiter, peer_host

    assert peer_host("ipv4:10.0.0.7:51234") == "ipv4:10.0.0.7" and peer_host("ipv6:[::1]:5") == "ipv6:[::1]"
    lim = FailureLimiter(max_failures=3, window_s=0.3)
    for _ in range(3):
        lim.failed("ipv4:10.0.0.7")
    assert lim.blocked("ipv4:10.0.0.7") and not lim.blocked("ipv4:10.0.0.8")
    time.sleep(0.35)
    assert not lim.blocked("ipv4:10.0.0.7")
    # a burst of checks at once: at most max_in_flight of one host may derive keys, the others only the cheap checks
    lim = FailureLimiter(max_in_flight=2)
    assert lim.begin_costly("h1") and lim.begin_costly("h1") and not lim.begin_costly("h1")
    assert lim.begin_costly("h2")  # another host has its own
    lim.end_costly("h1")
    assert lim.begin_costly("h1") and not lim.begin_costly("h1")

    good = auth.new_token()
    path = tmp_path / "tokens.json"
    path.write_text(json.dumps({"agents": {"robot-a": auth.hash_token(good, "pbkdf2", iterations=10_000)}}))
    store = auth.AgentTokens(path)
    assert store.identify(good, cheap_only=True) is None  # never verified: no derivation allowed
    assert store.identify(good) == "robot-a"
    assert store.identify(good, cheap_only=True) == "robot-a"  # verified once: a dictionary lookup

    srv = serve(ServerOptions(port=0, agent_tokens_file=str(path)), data_dir=str(tmp_path / "data"))
    try:
        with FusionClient(srv.address, token=good, timeout_s=10) as robot:
            robot.stats()  # the robot's token is verified once
            ch = grpc.insecure_channel(srv.address)
            stub = fusion_pb2_grpc.FusionStub(ch)
            codes, msgs = [], []
            for i in range(25):
                try:
                    stub.GetStats(fusion_pb2.StatsRequest(), timeout=10,
                                  metadata=(("authorization", f"Bearer wrong-{i}"),))
                except grpc.RpcError as e:
                    codes.append(e.code())
                    msgs.append(e.details())
            ch.close()
            assert set(codes) == {grpc.StatusCode.UNAUTHENTICATED} and len(codes) == 25
            assert "only known credentials" in msgs[-1] and "only known credentials" not in msgs[0]
            assert "robot-a" not in json.dumps(msgs)
            robot.stats()  # same address, still served
    finally:
        srv.stop(0.5)
