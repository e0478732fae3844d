"""A bounded protocol fuzzer for rig servers (loopback only): hostile bytes, envelopes and peers.

:func:`fuzz` drives one server (``magctl rig serve-sim``, or a lab's server speaking
docs/rig-protocol.md) with an **owner** session that configures, activates, writes valid
commands and then goes silent, while hostile channels fire between its requests:

* ``mutate`` — a REQ socket sending valid requests mutated at the JSON level (wrong types,
  huge or non-finite numbers, booleans for integers, missing or extra keys, commands beyond
  the limits) and at the byte level (flips, truncation, insertion); half of them carry the
  owner's session token, so the validator is tested behind the ownership check too;
* ``stranger`` — a REQ socket with valid-looking commands and no or a wrong session;
* ``noise`` — random bytes and oversized messages on a REQ socket;
* ``envelope`` — DEALER messages without the REQ delimiter, several body frames, empty ones;
* ``tcp`` — raw TCP: random blobs, ZMTP/1.0 bytes, a greeting cut short, and a ZMTP/3.0 peer that
  completes the handshake and sends half a frame, then stays connected (frozen) for the round.

Checks, every round: every REQ message got a well-formed reply (``ok`` with the request's id, or
an error with a known code); the server process is alive; the coils were zeroed by the watchdog
after the last valid command. In lock-step the bound ``watchdog + one frame`` is checked in simulated
time, exactly; in real time the server's own measure of the trip is recorded (``watchdog_after_s``)
and judged by the benchmark (``benchmarks/bench_rig_fuzz.py``), not here, because a wall-clock bound
depends on the machine's load — real time fails a round only if the coils stay on for the round's
whole budget (5 s). The server applied exactly the commands this fuzzer saw
accepted, each within the limits. Loops are bounded in count and time.
"""

from __future__ import annotations

import json
import random
import socket
import time
from dataclasses import dataclass, field
from urllib.parse import urlparse

import zmq

from magctl.rig import protocol as P
from magctl.rig.interface import Command, CommandRejected, RigLimits

KNOWN_CODES = {P.BAD_JSON, P.TOO_LARGE, P.BAD_VERSION, P.BAD_REQUEST, P.BAD_COMMAND, P.BAD_STATE, P.NOT_OWNER,
               P.BAD_ENVELOPE, P.INTERNAL, P.UNAUTHORISED, P.DEVICE_FAULT}
WEIRD = [None, True, False, 0, -1, 1, 1.0, 1.5, -0.0, 2**63, -(2**63) - 1, 10**30, 1e308, -1e308, 5e-324, "", "1",
         "NaN", "Infinity", [], [1], [1, 2, 3], {}, {"a": 1}, [[[[]]]], "x" * 300, "\u0000", "\udcff"[:0] + "é"]


@dataclass
class FuzzReport:
    """What the fuzzer sent and found (counts; ``failures`` lists the first problems seen)."""

    messages: int = 0
    by_channel: dict = field(default_factory=dict)
    replies: int = 0
    error_codes: dict = field(default_factory=dict)
    unanswered: int = 0
    malformed_replies: int = 0
    rounds: int = 0
    owner_disturbed: int = 0
    watchdog_checked: int = 0
    watchdog_late: int = 0
    watchdog_after_s: list = field(default_factory=list)
    accepted_writes: int = 0
    server_applied: int | None = None
    invalid_applied: int = 0
    server_exits: int = 0
    failures: list = field(default_factory=list)
    elapsed_s: float = 0.0

    def fail(self, message: str) -> None:
        if len(self.failures) < 20:
            self.failures.append(message)

    @property
    def ok(self) -> bool:
        return not self.failures

    def to_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "watchdog_after_s"}
        after = sorted(self.watchdog_after_s)
        if after:
            d["watchdog_after_ms"] = {"min": after[0] * 1e3, "p50": after[len(after) // 2] * 1e3,
                                      "p99": after[min(len(after) - 1, int(0.99 * len(after)))] * 1e3,
                                      "max": after[-1] * 1e3, "n": len(after)}
        return d


class _Req:
    """A REQ socket with a reply timeout; a lost reply recreates the socket."""

    def __init__(self, ctx, address, timeout_ms):
        self.ctx, self.address, self.timeout_ms = ctx, address, timeout_ms
        self.sock = None
        self._open()

    def _open(self):
        if self.sock is not None:
            self.sock.close(0)
        self.sock = self.ctx.socket(zmq.REQ)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.RCVTIMEO, self.timeout_ms)
        self.sock.setsockopt(zmq.SNDTIMEO, self.timeout_ms)
        self.sock.connect(self.address)

    def ask(self, raw) -> bytes | None:
        try:
            if isinstance(raw, list):
                self.sock.send_multipart(raw)
            else:
                self.sock.send(raw)
            return self.sock.recv()
        except zmq.Again:
            self._open()
            return None

    def close(self):
        self.sock.close(0)


def _tcp_target(address: str) -> tuple[str, int]:
    u = urlparse(address)
    if u.scheme != "tcp" or u.hostname not in ("127.0.0.1", "localhost", "::1"):
        raise ValueError(f"the fuzzer only talks to loopback tcp endpoints, not {address!r}")
    return u.hostname, u.port


ZMTP3_GREETING = b"\xff" + b"\x00" * 8 + b"\x7f" + b"\x03\x00" + b"NULL" + b"\x00" * 16 + b"\x00" + b"\x00" * 31
_READY_BODY = b"\x05READY" + b"\x0bSocket-Type" + (6).to_bytes(4, "big") + b"DEALER"
ZMTP3_READY = b"\x04" + bytes([len(_READY_BODY)]) + _READY_BODY
ZMTP10_BYTES = b"\x01\x00" + b"\x0b\x00" + b"0123456789"  # 14 bytes: identity frame + a frame of a ZMTP/1.0 peer


def valid_command(rng: random.Random, limits: RigLimits) -> dict:
    """A command well inside the limits (what the owner sends)."""
    import math

    a = rng.uniform(0, 2 * math.pi)
    b = rng.uniform(0.2, 0.9) * limits.b_static_max
    return {"b_static_T": [b * math.cos(a), b * math.sin(a)], "b_osc_T": rng.uniform(0, 0.3) * limits.b_osc_max,
            "freq_Hz": rng.uniform(0, 0.5) * limits.freq_max}


class Fuzzer:
    def __init__(self, address: str, *, seed: int = 0, limits: RigLimits | None = None, lockstep: bool = True,
                 watchdog: float = 0.1, period: float = 1 / 30, timeout_ms: int = 2000, alive=None):
        self.host, self.port = _tcp_target(address)
        self.address, self.rng = address, random.Random(seed)
        self.limits = limits or RigLimits.from_params()
        self.lockstep, self.watchdog, self.period = lockstep, watchdog, period
        self.alive = alive or (lambda: True)
        self.ctx = zmq.Context()
        self.owner = _Req(self.ctx, address, timeout_ms)
        self.mutator = _Req(self.ctx, address, timeout_ms)
        self.stranger = _Req(self.ctx, address, timeout_ms)
        self.noise = _Req(self.ctx, address, timeout_ms)
        self.dealer = self.ctx.socket(zmq.DEALER)
        self.dealer.setsockopt(zmq.LINGER, 0)
        self.dealer.setsockopt(zmq.SNDTIMEO, timeout_ms)
        self.dealer.connect(address)
        self.frozen: list[socket.socket] = []
        self.session = None
        self.id = 0
        self.report = FuzzReport()

    # --- plumbing -----------------------------------------------------------------------------
    def close(self):
        for s in self.frozen:
            s.close()
        self.frozen.clear()
        for r in (self.owner, self.mutator, self.stranger, self.noise):
            r.close()
        self.dealer.close(0)
        self.ctx.term()

    def _count(self, channel: str, n: int = 1):
        self.report.messages += n
        self.report.by_channel[channel] = self.report.by_channel.get(channel, 0) + n

    def _request(self, op, **fields) -> dict:
        self.id += 1
        return P.request(op, self.id, **fields)

    def _check_reply(self, raw: bytes | None, sent_id, channel: str) -> dict | None:
        r = self.report
        if raw is None:
            r.unanswered += 1
            r.fail(f"{channel}: no reply within the timeout")
            return None
        r.replies += 1
        try:
            doc = json.loads(raw)
            assert isinstance(doc, dict) and doc.get("protocol") == P.PROTOCOL and doc.get("version") == P.VERSION
            assert isinstance(doc.get("ok"), bool)
            if not doc["ok"]:
                code = doc["error"]["code"]
                assert code in KNOWN_CODES and isinstance(doc["error"]["message"], str)
                r.error_codes[code] = r.error_codes.get(code, 0) + 1
            else:
                assert doc.get("id") == sent_id
        except (ValueError, AssertionError, KeyError, TypeError):
            r.malformed_replies += 1
            r.fail(f"{channel}: malformed reply {raw[:120]!r}")
            return None
        return doc

    def _ask(self, req: _Req, doc_or_raw, channel: str) -> dict | None:
        raw = doc_or_raw if isinstance(doc_or_raw, (bytes, list)) else json.dumps(doc_or_raw).encode()
        sent = doc_or_raw if isinstance(doc_or_raw, dict) else _try_json(raw)
        sent_id = sent.get("id") if isinstance(sent, dict) else None
        self._count(channel)
        reply = self._check_reply(req.ask(raw), sent_id, channel)
        if reply is not None and reply.get("ok") and isinstance(sent, dict) and sent.get("op") == "write":
            self._accepted_write(sent, channel)
        if reply is not None and reply.get("ok") and isinstance(sent, dict) and sent.get("op") == "deactivate":
            self.session = None
        return reply

    def _accepted_write(self, sent: dict, channel: str) -> None:
        self.report.accepted_writes += 1
        cmd = sent.get("cmd", {})
        try:
            self.limits.check(Command.from_values(cmd["b_static_T"], cmd["b_osc_T"], cmd["freq_Hz"]))
            ok = (type(sent.get("version")) is int and isinstance(cmd["b_static_T"], list)
                  and sent.get("session") == self.session and set(cmd) == {"b_static_T", "b_osc_T", "freq_Hz"})
        except (CommandRejected, KeyError, TypeError, ValueError):
            ok = False
        if not ok:
            self.report.invalid_applied += 1
            self.report.fail(f"{channel}: an invalid command was accepted: {json.dumps(sent)[:200]}")

    # --- owner --------------------------------------------------------------------------------
    def owner_call(self, op, **fields) -> dict | None:
        if self.session is not None and op != "hello":
            fields.setdefault("session", self.session)
        reply = self._ask(self.owner, self._request(op, **fields), "owner")
        if reply is not None and reply.get("ok") and op == "configure":
            self.session = reply["session"]
        return reply

    def owner_ready(self) -> bool:
        """Own the rig and have it active (re-claiming it after a hostile deactivate/takeover)."""
        st = self.owner_call("status")
        if st is None:
            return False
        if not st.get("session_owner"):
            self.session = None
            r = self.owner_call("configure", takeover=True)
            if r is None or not r.get("ok"):
                return False
            st = self.owner_call("status")
        if st["state"] != "active":
            r = self.owner_call("activate")
            return r is not None and r.get("ok")
        return True

    # --- hostile channels -----------------------------------------------------------------------
    def _mutated(self) -> bytes:
        rng = self.rng
        op = rng.choice(P.OPS + ("launch", ""))
        doc = self._request(op)
        if op == "write" or rng.random() < 0.2:
            doc["cmd"] = valid_command(rng, self.limits)
        if self.session is not None and rng.random() < 0.5:
            doc["session"] = self.session
        for _ in range(rng.randint(1, 3)):
            kind = rng.random()
            target = doc["cmd"] if "cmd" in doc and isinstance(doc["cmd"], dict) and rng.random() < 0.5 else doc
            keys = list(target)
            if kind < 0.45 and keys:
                target[rng.choice(keys)] = rng.choice(WEIRD)
            elif kind < 0.6 and keys:
                del target[rng.choice(keys)]
            elif kind < 0.7:
                target[rng.choice(["extra", "reset", "takeover", "session", "cmd", "b_osc_T"])] = rng.choice(WEIRD)
            elif kind < 0.85 and "cmd" in doc and isinstance(doc["cmd"], dict):
                # beyond a limit by a factor, or negative
                c = doc["cmd"]
                k = rng.choice(["b_static_T", "b_osc_T", "freq_Hz"])
                if k == "b_static_T" and isinstance(c.get(k), list) and len(c[k]) == 2:
                    c[k] = [x * rng.choice([-1, 2, 5, 1e6]) for x in c[k] if isinstance(x, (int, float))]
                elif isinstance(c.get(k), (int, float)):
                    c[k] = c[k] * rng.choice([-1, 3, 100, 1e9]) + rng.choice([0, 1e-3, 1.0])
            else:
                doc["version"] = rng.choice([float(P.VERSION), True, str(P.VERSION), P.VERSION - 1, P.VERSION + 1,
                                             0, -1, None])
        try:
            raw = json.dumps(doc, allow_nan=True).encode()
        except (ValueError, TypeError):
            raw = b"{}"
        if rng.random() < 0.3:
            raw = self._byte_mutation(raw)
        return raw

    def _byte_mutation(self, raw: bytes) -> bytes:
        rng = self.rng
        b = bytearray(raw)
        for _ in range(rng.randint(1, 4)):
            k = rng.random()
            i = rng.randrange(len(b) + 1)
            if k < 0.4 and b:
                b[min(i, len(b) - 1)] = rng.randrange(256)
            elif k < 0.6:
                b = b[:i]
            elif k < 0.8:
                b[i:i] = rng.choice([b"NaN", b"1e400", b"-", b"\xff\xfe", b"9" * rng.randint(20, 5000), b"[" * 50,
                                     b"{", b'"', b"\\u0000", b"true"])
            else:
                b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
        return bytes(b)

    def hostile(self, budget: int) -> None:
        """Send ``budget`` hostile messages over a random mix of channels."""
        rng = self.rng
        for _ in range(budget):
            ch = rng.random()
            if ch < 0.45:
                self._ask(self.mutator, self._mutated(), "mutate")
            elif ch < 0.55:
                session = rng.choice([None, "0" * 32, "not-a-session", (self.session or "x")[::-1]])
                op = rng.choice(["write", "activate", "deactivate", "configure"])
                fields = {"cmd": valid_command(rng, self.limits)} if op == "write" else {}
                if session is not None:
                    fields["session"] = session
                self._ask(self.stranger, self._request(op, **fields), "stranger")
            elif ch < 0.7:
                n = rng.choice([0, 1, 10, 100, 1000, P.MAX_MESSAGE_BYTES + rng.randint(1, 1000)])
                raw = rng.randbytes(n) if rng.random() < 0.7 else b"[" * n
                self._ask(self.noise, raw, "noise")
            elif ch < 0.8:
                parts = rng.choice([
                    [self._mutated()], [json.dumps(self._request("status")).encode()],
                    [b"", b"a", b"b"], [b"x"] * rng.randint(2, 6), [b""], [b"", b""],
                    [b"", json.dumps(self._request("write", cmd=valid_command(rng, self.limits))).encode()],
                ])
                self._count("envelope")
                try:
                    self.dealer.send_multipart(parts, zmq.NOBLOCK)
                except zmq.Again:
                    pass
                # replies (if any) are read and dropped
                while self.dealer.poll(0):
                    self.dealer.recv_multipart()
            elif ch < 0.85:
                self._ask(self.noise, [self._mutated(), b"second frame"], "multiframe")
            else:
                self._tcp(rng)

    def _tcp(self, rng) -> None:
        kind = rng.choice(["blob", "zmtp10", "greeting-cut", "half-frame", "greeting-blob"])
        self._count("tcp")
        try:
            s = socket.create_connection((self.host, self.port), timeout=1.0)
        except OSError as err:
            self.report.fail(f"tcp: cannot connect: {err}")
            return
        try:
            if kind == "blob":
                s.sendall(rng.randbytes(rng.choice([1, 14, 66, 200, 2000])))
            elif kind == "zmtp10":
                s.sendall(ZMTP10_BYTES)
            elif kind == "greeting-cut":
                s.sendall(ZMTP3_GREETING[: rng.randint(1, 63)])
            elif kind == "greeting-blob":
                s.sendall(ZMTP3_GREETING + rng.randbytes(rng.randint(1, 300)))
            else:
                # a ZMTP/3.0 DEALER that completes the handshake, then sends the delimiter and half a frame
                s.sendall(ZMTP3_GREETING + ZMTP3_READY + b"\x01\x00" + b"\x00\x64" + b'{"protocol": ')
        except OSError:
            pass
        if kind in ("half-frame", "greeting-cut") and len(self.frozen) < 8:
            self.frozen.append(s)  # stays connected, frozen, until the round ends
        else:
            s.close()

    # --- rounds -------------------------------------------------------------------------------
    def round(self, hostile_per_round: int) -> None:
        r = self.report
        rng = self.rng
        r.rounds += 1
        if not self.owner_ready():
            # someone else took the rig over between the owner's configure and activate (allowed: takeovers
            # are explicit); the round is skipped, the next one claims the rig again
            r.owner_disturbed += 1
            if r.owner_disturbed > max(10, r.rounds // 2):
                r.fail(f"the owner could not configure/activate the rig in {r.owner_disturbed} rounds")
            return
        before = self.owner_call("status")
        trips0 = before["watchdog_trips"] if before else 0
        # active phase: valid writes and reads, hostile messages between them
        for _ in range(rng.randint(1, 4)):
            if self.session is None:
                break
            self.owner_call("write", cmd=valid_command(rng, self.limits))
            self.hostile(rng.randint(0, max(1, hostile_per_round // 4)))
            self.owner_call("read")
        # silent phase: no valid command from now on; hostile traffic goes on
        st = self.owner_call("status")
        if st is None or st["command_age_s"] is None or st["state"] != "active" or st["coils_zero"]:
            self._end_round()
            return  # a hostile deactivate or takeover zeroed the coils already
        # the server's own age of the last valid command (on its clock: simulated time in lock-step, where
        # other clients' reads advance frames too) decides whether the coils were on for too long
        bound = self.watchdog + self.period + 1e-9
        judge_bound = self.lockstep
        deadline = time.monotonic() + 5.0
        too_long = None
        while time.monotonic() < deadline:
            self.hostile(rng.randint(0, 3))
            if self.lockstep:
                self.owner_call("read")
            else:
                time.sleep(0.01)
            st = self.owner_call("status")
            if st is None or st["coils_zero"] or st["state"] != "active":
                break
            if judge_bound and st["command_age_s"] is not None and st["command_age_s"] > bound:
                too_long = st
                break
        if too_long is not None:
            r.watchdog_late += 1
            r.fail(f"coils still on {too_long['command_age_s'] * 1e3:.1f} ms after the last valid command "
                   f"(bound {bound * 1e3:.1f} ms)")
        elif st is not None and st["watchdog_trips"] == trips0 + 1 and st["coils_zero"]:
            r.watchdog_checked += 1
            after = st["watchdog_tripped_after_s"]
            r.watchdog_after_s.append(after)
            if not self.watchdog < after or (judge_bound and after > bound):
                r.watchdog_late += 1
                r.fail(f"watchdog tripped after {after * 1e3:.1f} ms (bound {1e3 * (self.watchdog + self.period):.1f})")
        elif st is not None and st["state"] == "active" and not st["coils_zero"]:
            r.watchdog_late += 1
            r.fail(f"coils still on after the round's time budget: {st}")
        self._end_round()

    def _end_round(self):
        for s in self.frozen:
            s.close()
        self.frozen.clear()
        if not self.alive():
            self.report.server_exits += 1
            self.report.fail("the server process exited")

    def run(self, n_messages: int, time_budget: float, hostile_per_round: int = 40) -> FuzzReport:
        t0 = time.monotonic()
        try:
            while self.report.messages < n_messages and time.monotonic() - t0 < time_budget:
                self.round(hostile_per_round)
                if self.report.server_exits:
                    break
            st = self.owner_call("status")
            if st is not None:
                self.report.server_applied = st["commands_applied"]
                if st["commands_applied"] != self.report.accepted_writes:
                    self.report.fail(f"server applied {st['commands_applied']} commands, the fuzzer saw "
                                     f"{self.report.accepted_writes} accepted")
            if self.session is not None:
                self.owner_call("deactivate")
        finally:
            self.report.elapsed_s = time.monotonic() - t0
            self.close()
        return self.report


def _try_json(raw):
    try:
        return json.loads(raw)
    except (ValueError, TypeError, RecursionError):
        return None


def fuzz(address: str, n_messages: int, *, seed: int = 0, lockstep: bool = True, time_budget: float = 600.0,
         alive=None, watchdog: float = 0.1, period: float = 1 / 30, limits: RigLimits | None = None) -> FuzzReport:
    """Fuzz the server at ``address`` (loopback) with about ``n_messages`` messages; see the module doc."""
    return Fuzzer(address, seed=seed, lockstep=lockstep, alive=alive, watchdog=watchdog, period=period,
                  limits=limits).run(n_messages, time_budget)


def crowd(address: str, n_clients: int, stop, *, seed: int = 0, max_messages: int = 1_000_000) -> dict:
    """``n_clients`` threads of strangers (no session) sending mutated requests, noise and stranger
    commands until ``stop`` (a ``threading.Event``) is set or ``max_messages`` were sent in all; returns
    counts. Runs beside :func:`fuzz`, whose checks stay valid: a stranger never owns the rig."""
    import threading

    _tcp_target(address)
    counts = {"messages": 0, "replies": 0, "unanswered": 0, "malformed": 0, "accepted_writes": 0}
    lock = threading.Lock()

    def worker(k):
        f = Fuzzer.__new__(Fuzzer)
        f.rng, f.limits, f.session, f.id = random.Random(seed * 1000 + k), RigLimits.from_params(), None, 0
        ctx = zmq.Context()
        req = _Req(ctx, address, 2000)
        local = dict.fromkeys(counts, 0)
        try:
            while not stop.is_set() and counts["messages"] + local["messages"] < max_messages:
                choice = f.rng.random()
                if choice < 0.6:
                    raw = f._mutated()
                elif choice < 0.8:
                    raw = json.dumps(f._request("write", cmd=valid_command(f.rng, f.limits))).encode()
                else:
                    raw = f.rng.randbytes(f.rng.choice([0, 5, 100, 3000]))
                local["messages"] += 1
                reply = req.ask(raw)
                if reply is None:
                    local["unanswered"] += 1
                    continue
                local["replies"] += 1
                doc = _try_json(reply)
                if not isinstance(doc, dict) or not isinstance(doc.get("ok"), bool):
                    local["malformed"] += 1
                elif doc["ok"] and isinstance(_try_json(raw), dict) and _try_json(raw).get("op") == "write":
                    local["accepted_writes"] += 1
        finally:
            req.close()
            ctx.term()
            with lock:
                for key, v in local.items():
                    counts[key] += v

    threads = [threading.Thread(target=worker, args=(k,), daemon=True) for k in range(n_clients)]
    for t in threads:
        t.start()
    return {"threads": threads, "counts": counts}
