"""A coil driver made of function-generator channels over VISA (pyvisa): each coil amplifier's input is one
generator channel set to a DC offset plus a sine.

**No device-side deadline.** A function generator keeps its output when the host stops: if the control computer
hangs, crashes or loses the connection, the coils keep their last current indefinitely. :class:`VisaCoils` therefore
has ``device_deadline = False`` and ``deadline = None``, and coil safety rests on the host alone. The lab server
refuses such a driver unless the lab opts in explicitly; a lab that drives real coils with it needs its own
hardware interlock (an amplifier enable with a watchdog, a thermal cut-out) in front of the amplifiers.

**Channels.** Coil ``k`` is channel ``channels[k] = (instrument, channel number)`` of the instruments named by
``resources`` (an index into ``resources`` or the resource string itself); by default the channels of the
instruments in order, two per instrument (three 2-channel generators → six coils). The generator sets volts; the
amplifier turns them into amperes with its transconductance ``g_k`` (A/V), so for a setpoint
``i_k(t) = dc_k + ac_k · sin(2π f t)``:

* offset ``dc_k / g_k`` V;
* sine peak ``|ac_k / g_k|`` V, sent as ``amplitude_per_peak`` times that (2: the amplitude is peak-to-peak,
  ``VOLT:UNIT VPP``);
* phase 0° when ``ac_k / g_k > 0``, 180° when it is < 0 (the setpoint's signed amplitude; a zero amplitude keeps
  the phase it had); :meth:`VisaCoils.readback` maps 180° back to a negative amplitude and refuses any other phase;
* frequency ``f`` on every channel; at 0 Hz the setpoint is static (``sin 0 = 0``): the amplitudes are set to zero
  and the frequency is left as it was (generators refuse 0 Hz). A read-back reports 0 Hz when no channel has an
  amplitude.

**Phase between instruments.** The sign convention assumes every channel's sine has the same phase origin. Two
channels of one generator share it only after the generator aligns them (many need a command for it:
``ScpiDialect.phase_sync``); separate generators share it only with a common 10 MHz reference and a common
trigger. Without those, a setpoint's oscillation is not the one commanded. The driver cannot check this.

**Safety rules kept.** A setpoint is checked against ``current_limit`` (:meth:`CoilSetpoint.check`) before anything
is sent. Within a channel the offset and the amplitude change in the order whose intermediate state stays within
the larger of the old and new peak (so within the rating). Each channel's commands are followed by ``SYST:ERR?``; a
non-zero answer is a :class:`DeviceError` naming the instrument and channel, and every value sent is queried back
and compared (``confirm``). Only what changed since the last confirmed write is sent (:meth:`VisaCoils.readback`
always asks the instruments). The channels are written one after the other: for a few milliseconds some hold the
new setpoint and some the old one.

**Zero.** :meth:`VisaCoils.zero` sends offset 0 and amplitude 0 to every channel first and checks afterwards (fast),
on every instrument it can reach (a dead instrument does not stop the others), and leaves the outputs on: an
enabled output at 0 V holds the amplifier input at 0 V, while ``OUTP OFF`` opens the output (the amplifier input
floats, the relay clicks and wears). :meth:`VisaCoils.close` zeroes, then turns the outputs off.

**Dialect.** All commands are the templates of :class:`ScpiDialect` (the common function-generator dialect, as on
the Keysight 33500 and Rigol DG1000Z); a lab with another dialect passes its own. Real generators refuse a zero
amplitude (1 mVpp is a typical minimum) and an offset plus amplitude beyond their output range: such a refusal
surfaces as a :class:`DeviceError` from ``SYST:ERR?``, never silently.

**Simulation.** ``visa-sim.yaml`` beside this module defines three simulated 2-channel generators for pyvisa-sim::

    VisaCoils(SIM_RESOURCES, transconductance=1.0, current_limit=2.0, backend=sim_backend())

pyvisa and pyvisa-sim are imported only when a driver opens.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magctl.rig.devices.base import CoilDriver, CoilReadback, CoilSetpoint, DeviceError

SIM_DEFINITIONS = Path(__file__).with_name("visa-sim.yaml")
"""pyvisa-sim definitions of three 2-channel function generators (:data:`SIM_RESOURCES`)."""

SIM_RESOURCES = (
    "USB0::0x1111::0x2222::FG0001::INSTR",
    "USB0::0x1111::0x2222::FG0002::INSTR",
    "TCPIP0::192.0.2.3::inst0::INSTR",
)
"""The resource names of the simulated generators in :data:`SIM_DEFINITIONS`."""


def sim_backend(definitions: str | Path = SIM_DEFINITIONS) -> str:
    """The pyvisa backend string of a pyvisa-sim definitions file (absolute, so the working directory does not
    matter)."""
    return f"{Path(definitions).resolve()}@sim"


@dataclass(frozen=True)
class ScpiDialect:
    """The SCPI commands :class:`VisaCoils` sends: ``{ch}`` is the channel number, ``{value}`` the number and
    ``{state}`` ON or OFF. The defaults are the common function-generator dialect; override fields for another."""

    identify: str = "*IDN?"
    error: str = "SYST:ERR?"
    """Answers ``<code>,<message>``; code 0 is no error."""
    setup: tuple[str, ...] = ("SOUR{ch}:FUNC SIN", "SOUR{ch}:VOLT:UNIT VPP", "OUTP{ch}:LOAD INF")
    """Sent to every channel by ``open``: a sine, amplitudes in Vpp, and the output voltage as set into a high
    impedance (a generator set for a 50 Ω load puts twice the set voltage on an amplifier's high-impedance input)."""
    function_query: str = "SOUR{ch}:FUNC?"
    function_sine: tuple[str, ...] = ("SIN", "SINUSOID")
    """Answers to ``function_query`` that mean a sine."""
    frequency: str = "SOUR{ch}:FREQ {value:.10g}"
    frequency_query: str = "SOUR{ch}:FREQ?"
    amplitude: str = "SOUR{ch}:VOLT {value:.10g}"
    amplitude_query: str = "SOUR{ch}:VOLT?"
    amplitude_per_peak: float = 2.0
    """Amplitude sent per volt of sine peak: 2 for peak-to-peak (``VOLT:UNIT VPP``), 1 for peak."""
    offset: str = "SOUR{ch}:VOLT:OFFS {value:.10g}"
    offset_query: str = "SOUR{ch}:VOLT:OFFS?"
    phase: str = "SOUR{ch}:PHAS {value:.10g}"
    """Degrees."""
    phase_query: str = "SOUR{ch}:PHAS?"
    phase_sync: tuple[str, ...] = ()
    """Sent once to an instrument after a frequency or phase change on it, to align its channels' phases (e.g.
    ``("PHAS:SYNC",)`` on a Keysight 33500); none in the common dialect."""
    output: str = "OUTP{ch} {state}"
    output_query: str = "OUTP{ch}?"
    output_on: tuple[str, ...] = ("1", "ON")
    """Answers to ``output_query`` that mean on."""


def _one_line(err: BaseException) -> str:
    """An exception as one line: its type and the last meaningful line of its message (pyvisa-sim wraps a whole
    traceback into the message of a definitions-file error)."""
    text = str(err).replace("\\n", "\n").replace("\\'", "'")
    lines = [t.strip() for t in text.splitlines() if t.strip(" '\"")]
    name = type(err).__name__
    if not lines:
        return name
    return lines[-1] if lines[-1].startswith(name) else f"{name}: {lines[-1]}"


def _float(text: str) -> float:
    return float(text.strip().strip('"'))


class VisaCoils(CoilDriver):
    """Coil amplifiers driven by function-generator channels over VISA (see the module docstring).

    Parameters
    ----------
    resources : sequence of str
        VISA resource names of the instruments.
    transconductance : float or sequence of float
        Each amplifier's gain, A per V at its input (nonzero; negative for an inverting amplifier).
    current_limit : float or sequence of float
        Each coil's rating, A.
    channels : sequence of (int or str, int), optional
        Coil ``k`` → (instrument: index into ``resources`` or its resource name, channel number). Default: two
        channels per instrument, in order.
    backend : str
        pyvisa backend (``""`` the system VISA, ``"@py"`` pyvisa-py, ``"<definitions.yaml>@sim"`` pyvisa-sim).
    freq_max : float
        Highest sine frequency accepted, Hz.
    dialect : ScpiDialect
        The command templates.
    timeout : float
        VISA I/O timeout, s.
    confirm : bool
        Query every value sent back and compare it (False for instruments that do not answer value queries:
        writes are then confirmed by ``SYST:ERR?`` alone and :meth:`readback` returns None).
    tolerance : float
        Largest difference between a voltage sent and the one queried back, V (the instruments' resolution).
    idn_contains : str, optional
        A text every instrument's ``*IDN?`` answer must contain (e.g. the model).
    name : str
        The device's name in messages.
    """

    device_deadline = False
    deadline = None

    def __init__(self, resources: Sequence[str], transconductance, current_limit, *,
                 channels: Sequence[tuple[int | str, int]] | None = None, backend: str = "",
                 freq_max: float = 1000.0, dialect: ScpiDialect | None = None, timeout: float = 2.0,
                 confirm: bool = True, tolerance: float = 1e-3, idn_contains: str | None = None,
                 read_termination: str = "\n", write_termination: str = "\n", name: str = "visa-coils"):
        self.name = name
        self.resources = tuple(str(r) for r in resources)
        if not self.resources:
            raise ValueError(f"{name}: no VISA resources")
        if channels is None:
            channels = [(i, c) for i in range(len(self.resources)) for c in (1, 2)]
        self.channels = tuple((self._instrument_index(inst), int(ch)) for inst, ch in channels)
        if len(set(self.channels)) != len(self.channels):
            raise ValueError(f"{name}: a generator channel is mapped to more than one coil: {self.channels}")
        self.n_channels = len(self.channels)
        n = self.n_channels
        self.transconductance = np.broadcast_to(np.asarray(transconductance, dtype=float), (n,)).copy()
        if not np.all(np.isfinite(self.transconductance)) or np.any(self.transconductance == 0):
            raise ValueError(f"{name}: transconductances must be finite and nonzero, got {self.transconductance}")
        self.current_limit = np.broadcast_to(np.asarray(current_limit, dtype=float), (n,)).copy()
        self.freq_max = float(freq_max)
        self.dialect = dialect or ScpiDialect()
        self.backend = backend
        self.timeout = float(timeout)
        self.confirm = bool(confirm)
        self.tolerance = float(tolerance)
        self.idn_contains = idn_contains
        self.read_termination = read_termination
        self.write_termination = write_termination
        self.identities: list[str] = []
        """The instruments' ``*IDN?`` answers (after :meth:`open`)."""
        self._inst: list | None = None
        # what each channel was last confirmed to hold (volts, degrees, Hz); None: unknown, send everything
        self._state: list[dict] | None = None

    def _instrument_index(self, inst: int | str) -> int:
        if isinstance(inst, str):
            if inst not in self.resources:
                raise ValueError(f"{self.name}: channel on {inst!r}, which is not among the resources")
            return self.resources.index(inst)
        if not 0 <= int(inst) < len(self.resources):
            raise ValueError(f"{self.name}: instrument index {inst} outside 0..{len(self.resources) - 1}")
        return int(inst)

    def _where(self, k: int) -> str:
        i, ch = self.channels[k]
        return f"{self.resources[i]} channel {ch} (coil {k})"

    # --- I/O -------------------------------------------------------------------------------------------------
    def _send(self, i: int, command: str, where: str) -> None:
        try:
            self._inst[i].write(command)
        except Exception as err:  # pyvisa raises VisaIOError, InvalidSession, OSError, ...
            raise DeviceError(self.name, f"{where}: {command!r} failed: {_one_line(err)}") from err

    def _ask(self, i: int, command: str, where: str) -> str:
        try:
            answer = self._inst[i].query(command)
        except Exception as err:
            raise DeviceError(self.name, f"{where}: {command!r} failed: {_one_line(err)}") from err
        if not answer.strip():
            raise DeviceError(self.name, f"{where}: no answer to {command!r}")
        return answer.strip()

    def _ask_float(self, i: int, command: str, where: str) -> float:
        answer = self._ask(i, command, where)
        try:
            return _float(answer)
        except ValueError:
            raise DeviceError(self.name, f"{where}: {command!r} answered {answer!r}, not a number") from None

    def _errors(self, i: int, where: str) -> list[str]:
        """Empty the instrument's error queue; the errors it held."""
        errors = []
        for _ in range(32):
            answer = self._ask(i, self.dialect.error, where)
            try:
                code = int(answer.split(",")[0].strip())
            except ValueError:
                raise DeviceError(self.name, f"{where}: unreadable error report {answer!r}") from None
            if code == 0:
                break
            errors.append(answer)
        return errors

    def _check_errors(self, i: int, where: str, after: str) -> None:
        """Raise :class:`DeviceError` when the instrument's error queue is not empty (and empty it)."""
        errors = self._errors(i, where)
        if errors:
            more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
            raise DeviceError(self.name, f"{where}: the instrument reports {errors[0]}{more} after {after}")

    def _channel_commands(self, k: int, commands: list[tuple[str, dict]]) -> None:
        """Send ``(template, fields)`` commands to coil ``k``'s channel, check the error queue, then query each value
        back (templates with ``{value}`` that have a query)."""
        i, ch = self.channels[k]
        where = self._where(k)
        if not commands:
            return
        texts = [t.format(ch=ch, **f) for t, f in commands]
        for text in texts:
            self._send(i, text, where)
        self._check_errors(i, where, " / ".join(texts))
        if self.confirm:
            queries = {self.dialect.frequency: (self.dialect.frequency_query, "freq"),
                       self.dialect.amplitude: (self.dialect.amplitude_query, "volt"),
                       self.dialect.offset: (self.dialect.offset_query, "volt"),
                       self.dialect.phase: (self.dialect.phase_query, "phase")}
            for template, fields in commands:
                if template not in queries:
                    continue
                query, kind = queries[template]
                got = self._ask_float(i, query.format(ch=ch), where)
                want = fields["value"]
                if kind == "phase":
                    ok = abs((got - want + 180.0) % 360.0 - 180.0) <= 0.5
                elif kind == "freq":
                    ok = abs(got - want) <= 1e-6 * abs(want) + 1e-6
                else:
                    ok = abs(got - want) <= self.tolerance + 1e-6 * abs(want)
                if not ok:
                    raise DeviceError(self.name, f"{where}: sent {template.format(ch=ch, **fields)!r} but the "
                                                 f"instrument holds {got:.6g}")

    # --- CoilDriver ---------------------------------------------------------------------------------------------
    def open(self) -> None:
        """Connect to every instrument, check ``*IDN?``, empty the error queues, set every channel up
        (``setup``), zero it and turn its output on. Raise :class:`DeviceError` naming the device and the resource
        that is missing or fails."""
        if self._inst is not None:
            return
        try:
            import pyvisa
        except ImportError as err:
            raise DeviceError(self.name, f"pyvisa is not installed ({_one_line(err)})") from err
        try:
            rm = pyvisa.ResourceManager(self.backend)
        except Exception as err:
            raise DeviceError(self.name, f"cannot load the VISA backend {self.backend!r}: {_one_line(err)}") from err
        self._inst = []
        self.identities = []
        try:
            for i, res in enumerate(self.resources):
                try:
                    inst = rm.open_resource(res, read_termination=self.read_termination,
                                            write_termination=self.write_termination)
                    inst.timeout = self.timeout * 1000.0
                    self._inst.append(inst)
                    with warnings.catch_warnings():
                        # a missing resource under pyvisa-sim answers "" with a termination warning: reported below
                        warnings.simplefilter("ignore", UserWarning)
                        idn = inst.query(self.dialect.identify).strip()
                except Exception as err:
                    raise DeviceError(self.name, f"no instrument at {res}: {_one_line(err)}") from err
                if not idn:
                    # pyvisa-sim (and some VISA libraries) open a resource that is not there without an error
                    raise DeviceError(self.name, f"no instrument at {res}: no answer to {self.dialect.identify!r}")
                if self.idn_contains is not None and self.idn_contains not in idn:
                    raise DeviceError(self.name, f"{res} is {idn!r}, not a {self.idn_contains!r}")
                self.identities.append(idn)
                self._errors(i, res)  # left from before: not ours
            d = self.dialect
            for k in range(self.n_channels):
                # offset first: it is volts whatever the amplitude unit was; the amplitude after VOLT:UNIT
                self._channel_commands(k, [(d.offset, {"value": 0.0})] + [(t, {}) for t in d.setup]
                                       + [(d.amplitude, {"value": 0.0}), (d.phase, {"value": 0.0}),
                                          (d.output, {"state": "ON"})])
                if self.confirm:
                    self._confirm_setup(k)
            self._state = [{"offset": 0.0, "amplitude": 0.0, "phase": 0.0, "freq": None}
                           for _ in self.channels]
        except BaseException:
            self._release()
            raise

    def _confirm_setup(self, k: int) -> None:
        i, ch = self.channels[k]
        where = self._where(k)
        func = self._ask(i, self.dialect.function_query.format(ch=ch), where).strip('"').upper()
        if func not in self.dialect.function_sine:
            raise DeviceError(self.name, f"{where}: function is {func!r}, not a sine")
        out = self._ask(i, self.dialect.output_query.format(ch=ch), where).upper()
        if out not in self.dialect.output_on:
            raise DeviceError(self.name, f"{where}: output is {out!r} after turning it on")

    def _require_open(self) -> None:
        if self._inst is None:
            raise DeviceError(self.name, "not open")

    def settings(self, setpoint: CoilSetpoint) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The instrument settings of a setpoint: (offset V, amplitude as sent, phase °) per coil. At 0 Hz the
        amplitudes are 0 (the setpoint is static); a zero amplitude has phase NaN (kept as it is)."""
        g = self.transconductance
        offset = setpoint.dc / g + 0.0  # + 0.0: no "-0" sent
        peak = setpoint.ac / g if setpoint.freq > 0 else np.zeros(self.n_channels)
        amplitude = np.abs(peak) * self.dialect.amplitude_per_peak + 0.0
        phase = np.where(peak > 0, 0.0, np.where(peak < 0, 180.0, np.nan))
        return offset, amplitude, phase

    def write(self, setpoint: CoilSetpoint) -> None:
        """Check ``setpoint`` against the ratings, then send each channel what changed since the last confirmed
        write (frequency, phase, then offset and amplitude in the order that keeps the intermediate peak within
        the rating), check ``SYST:ERR?`` and query the values back. Raise :class:`DeviceError` naming the
        instrument and channel when one is refused or not confirmed (the channels before it are then set)."""
        self._require_open()
        setpoint.check(self.current_limit, self.freq_max, self.name)
        d = self.dialect
        offset, amplitude, phase = self.settings(setpoint)
        state = self._state
        self._state = None  # unknown until confirmed
        if state is None:
            state = [{"offset": math.nan, "amplitude": math.nan, "phase": math.nan, "freq": None}
                     for _ in self.channels]
        synced = set()
        for k, (i, _ch) in enumerate(self.channels):
            s = dict(state[k])
            commands = []
            if setpoint.freq > 0 and s["freq"] != setpoint.freq:
                commands.append((d.frequency, {"value": setpoint.freq}))
                s["freq"] = setpoint.freq
            if not math.isnan(phase[k]) and s["phase"] != phase[k]:
                commands.append((d.phase, {"value": float(phase[k])}))
                s["phase"] = float(phase[k])
            new_offset = (d.offset, {"value": float(offset[k])}) if s["offset"] != offset[k] else None
            new_amplitude = (d.amplitude, {"value": float(amplitude[k])}) if s["amplitude"] != amplitude[k] else None
            # |new offset| <= |old offset|: offset first, the intermediate (new offset, old amplitude) is within the
            # old peak; else amplitude first, the intermediate (old offset, new amplitude) is within the new peak
            offset_first = math.isnan(s["offset"]) or abs(offset[k]) <= abs(s["offset"])
            pair = [new_offset, new_amplitude] if offset_first else [new_amplitude, new_offset]
            commands += [c for c in pair if c is not None]
            s["offset"], s["amplitude"] = float(offset[k]), float(amplitude[k])
            self._channel_commands(k, commands)
            state[k] = s
            if d.phase_sync and any(t in (d.frequency, d.phase) for t, _ in commands):
                synced.add(i)
        for i in sorted(synced):
            for text in d.phase_sync:
                self._send(i, text, self.resources[i])
            self._check_errors(i, self.resources[i], " / ".join(d.phase_sync))
        self._state = state

    def zero(self) -> None:
        """Every offset and amplitude to 0 V (outputs stay on, holding the amplifier inputs at 0 V): first sent to
        every channel of every instrument that answers, then checked with ``SYST:ERR?`` and queried back. Raise
        :class:`DeviceError` listing what failed, after trying every instrument."""
        self._require_open()
        d = self.dialect
        keep = self._state or [{"phase": math.nan, "freq": None}] * self.n_channels
        self._state = None
        failed, dead = [], set()
        for k, (i, ch) in enumerate(self.channels):
            if i in dead:
                continue
            try:
                self._send(i, d.amplitude.format(ch=ch, value=0.0), self._where(k))
                self._send(i, d.offset.format(ch=ch, value=0.0), self._where(k))
            except DeviceError as err:
                dead.add(i)  # do not wait out its timeout once per channel
                failed.append(str(err).removeprefix(f"{self.name}: "))
        for i in sorted(set(range(len(self.resources))) - dead):
            ks = [k for k, (j, _) in enumerate(self.channels) if j == i]
            try:
                self._check_errors(i, ", ".join(self._where(k) for k in ks), "zeroing")
                for k in ks if self.confirm else []:
                    ch = self.channels[k][1]
                    for query in (d.amplitude_query, d.offset_query):
                        got = self._ask_float(i, query.format(ch=ch), self._where(k))
                        if abs(got) > self.tolerance:
                            raise DeviceError(self.name, f"{self._where(k)}: {query.format(ch=ch)!r} is {got:.6g} "
                                                         f"after zeroing")
            except DeviceError as err:
                failed.append(str(err).removeprefix(f"{self.name}: "))
        if failed:
            raise DeviceError(self.name, "zero not confirmed: " + "; ".join(failed))
        self._state = [{"offset": 0.0, "amplitude": 0.0, "phase": s["phase"], "freq": s["freq"]} for s in keep]

    def readback(self) -> CoilReadback | None:
        """The outputs as the instruments report them (None without ``confirm``). A channel whose output is off
        reports zero. Raise :class:`DeviceError` when a channel is not a sine, has a phase other than 0° or 180°, or
        the channels with an amplitude run at different frequencies."""
        self._require_open()
        if not self.confirm:
            return None
        d = self.dialect
        n = self.n_channels
        dc, ac, freqs = np.zeros(n), np.zeros(n), []
        for k, (i, ch) in enumerate(self.channels):
            where = self._where(k)
            if self._ask(i, d.output_query.format(ch=ch), where).upper() not in d.output_on:
                continue
            func = self._ask(i, d.function_query.format(ch=ch), where).strip('"').upper()
            if func not in d.function_sine:
                raise DeviceError(self.name, f"{where}: function is {func!r}, not a sine")
            g = self.transconductance[k]
            dc[k] = self._ask_float(i, d.offset_query.format(ch=ch), where) * g
            peak = self._ask_float(i, d.amplitude_query.format(ch=ch), where) / d.amplitude_per_peak
            if peak == 0:
                continue
            phase = self._ask_float(i, d.phase_query.format(ch=ch), where) % 360.0
            if min(phase, 360.0 - phase) <= 0.5:
                sign = 1.0
            elif abs(phase - 180.0) <= 0.5:
                sign = -1.0
            else:
                raise DeviceError(self.name, f"{where}: phase {phase:.4g}° is neither 0° nor 180°")
            ac[k] = sign * peak * g
            freqs.append((k, self._ask_float(i, d.frequency_query.format(ch=ch), where)))
        freq = freqs[0][1] if freqs else 0.0
        for k, f in freqs:
            if abs(f - freq) > 1e-6 * freq + 1e-6:
                raise DeviceError(self.name, f"{self._where(k)}: runs at {f:.6g} Hz, {self._where(freqs[0][0])} "
                                             f"at {freq:.6g} Hz")
        return CoilReadback(CoilSetpoint(dc, ac, freq))

    def close(self) -> None:
        """Zero the outputs and turn them off (best effort), then release the instruments (idempotent). The
        resource manager is left open: pyvisa shares it between all users of the same backend."""
        if self._inst is None:
            return
        try:
            self.zero()
        except DeviceError:
            pass
        for k, (i, ch) in enumerate(self.channels):
            try:
                self._send(i, self.dialect.output.format(ch=ch, state="OFF"), self._where(k))
            except DeviceError:
                pass
        self._release()

    def _release(self) -> None:
        for inst in self._inst or []:
            try:
                inst.close()
            except Exception:
                pass
        self._inst = None
        self._state = None
