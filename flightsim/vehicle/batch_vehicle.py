"""N JSBSim vehicles flown through their autopilot responses together, one control step at a time.

Each :class:`~flightsim.vehicle.quadrotor.Vehicle` keeps its own JSBSim instance (JSBSim has no batched
integrator), but everything around ``FGFDMExec.run()`` is done for all N vehicles in one compiled
call per physics step: the autopilot response model (:mod:`flightsim.vehicle.autopilot_response`, every
chunk), the cascaded controller (:func:`flightsim.vehicle.control.control_step`, the same compiled
function), the motor lag and the unit conversions. What is left in Python per vehicle and physics
step is reading 11 properties, writing 5 and ``run()``.

The arithmetic is :func:`flightsim.vehicle.autopilot_response.fly` and ``Vehicle._advance`` operation by
operation, with the response's estimate noise drawn from the same generator in the same order, so
a batch flies the numbers N separate vehicles fly (tests/flightsim/test_batch_env.py).

While a batch flies them, it holds the vehicles' motor thrusts and the responses' command queues;
the controllers' memories and the responses' state vectors are shared with the objects (views).
"""

from __future__ import annotations

import math
import operator
from collections import deque

import numpy as np
from numba import njit

from flightsim.vehicle.autopilot_response import (
    _INNER_DT,
    _N_STATE,
    _P_NAMES,
    _S_AX,
    _S_AY,
    _S_BX,
    _S_BY,
    _S_MX,
    _S_MY,
    _S_R,
    _S_VX,
    _S_VY,
    CHUNK_S,
    AutopilotResponse,
)
from flightsim.vehicle.autopilot_response import _advance as _response_advance
from flightsim.vehicle.control import control_step, wrap_angle
from flightsim.vehicle.quadrotor import (
    _FT,
    _LBF_PER_N,
    _LBFFT_PER_NM,
    MAX_ROTOR_THRUST_N,
    YAW_MOMENT_PER_THRUST_M,
    Vehicle,
)

_QUEUE = 8  # pending commands per response; a command is due within one step, so 2 at most
_N_READ = 11  # properties the controller reads per physics step (Vehicle._get_flight)
_N_WRITE = 5  # four rotor thrusts and the rotor-drag yaw moment


class VehicleBatch:
    """N vehicles (same rates and controller) flown one control period at a time.

    :param vehicles: the vehicles; each keeps its JSBSim instance and is reset as usual, after
        which :meth:`load` takes its new state (and its new response, if any)
    """

    def __init__(self, vehicles: list[Vehicle]) -> None:
        first = vehicles[0].config
        for v in vehicles:
            if (v.config.physics_hz, v.config.control_hz) != (first.physics_hz, first.control_hz):
                raise ValueError("a vehicle batch needs one physics and one control rate")
        self.vehicles = vehicles
        n = self.n = len(vehicles)
        self._steps = first.physics_hz // first.control_hz
        chunk = CHUNK_S * first.physics_hz
        self._chunk = round(chunk)
        if abs(chunk - self._chunk) > 1e-9 or self._steps % self._chunk:
            raise ValueError(f"a control period must be a whole number of {CHUNK_S} s response chunks")
        self._dt = vehicles[0]._dt
        self._lag = np.array([v._lag for v in vehicles])
        self.memory = np.zeros((n, vehicles[0].controller.memory.size))
        self.gains = np.array([v.controller.gains for v in vehicles])
        self._limit = np.array(
            [v.controller.config.max_rotor_thrust_n > MAX_ROTOR_THRUST_N for v in vehicles]
        )
        self.thrust = np.zeros((n, 4))
        self._armed = np.zeros(n, dtype=np.bool_)
        self._get = [g for v in vehicles for g in v._get_flight]
        self._set = [s for v in vehicles for s in (*v._set_rotor, v._set_yaw_moment)]
        self._run = [v._run for v in vehicles]
        # the response models (a row per vehicle; has_response False = the ideal autopilot)
        self.has_response = np.zeros(n, dtype=np.bool_)
        self.x = np.zeros((n, _N_STATE))
        self.p = np.zeros((n, len(_P_NAMES)))
        self._queue = np.zeros((n, _QUEUE, 4))
        self._queue_len = np.zeros(n, dtype=np.int64)
        self._time = np.zeros(n)
        self._cmd = np.zeros((n, 3))
        self._delay = np.zeros(n)
        self._drag = np.zeros(n)
        self._noisy = np.zeros(n, dtype=np.bool_)
        self._decay = np.zeros(n)
        self._kick = np.zeros(n)
        self._rngs: list[np.random.Generator | None] = [None] * n
        self._noise = np.zeros((n, self._steps // self._chunk, 2))
        self._inner = max(1, round(CHUNK_S / _INNER_DT))
        self._h = CHUNK_S / self._inner
        for i in range(n):
            self.load(i, None)

    def load(self, i: int, response: AutopilotResponse | None) -> None:
        """Take vehicle ``i``'s state after its reset, and the response it flies through (None: ideal).

        :param i: the vehicle
        :param response: its freshly reset response model
        """
        v = self.vehicles[i]
        self.memory[i] = v.controller.memory
        v.controller.memory = self.memory[i]  # a view: the controller's own reset writes into it
        self.thrust[i] = v._thrust
        self._armed[i] = v._armed
        self.has_response[i] = response is not None
        self._rngs[i] = None
        if response is None:
            return
        if response._pending:
            raise ValueError("load a response right after its reset (it has commands pending)")
        self.x[i] = response._x
        response._x = self.x[i]  # a view, as the controller's memory
        self.p[i] = response._p
        self._queue_len[i] = 0
        self._time[i] = response._time
        self._cmd[i] = response._cmd
        params = response.params
        self._delay[i] = params.command_delay_s
        self._drag[i] = params.drag_per_s
        self._rngs[i] = response._rng
        self._noisy[i] = response._rng is not None
        if response._rng is not None:  # AutopilotResponse.setpoint's Ornstein-Uhlenbeck constants
            decay = math.exp(-CHUNK_S / params.est_vel_tau_s)
            self._decay[i] = decay
            self._kick[i] = params.est_vel_sigma * math.sqrt(1.0 - decay * decay)

    def fly(
        self, forward: np.ndarray, lateral: np.ndarray, yaw_rate: np.ndarray, altitude: np.ndarray
    ) -> None:
        """One control period for every vehicle: what :func:`flightsim.vehicle.autopilot_response.fly` does
        for each. Afterwards each vehicle's ``state`` is the new one.

        :param forward: ``(N,)`` commanded body velocity along the nose, m/s
        :param lateral: ``(N,)`` to the left, m/s
        :param yaw_rate: ``(N,)`` rad/s CCW
        :param altitude: ``(N,)`` altitude to hold, m
        """
        for i, rng in enumerate(self._rngs):
            if rng is not None:  # one standard_normal(2) per chunk, as AutopilotResponse.setpoint draws
                rng.standard_normal(out=self._noise[i])
        get, put, runs = self._get, self._set, self._run
        call = operator.call
        setpoints = np.zeros((self.n, 8))
        count = self.n * _N_READ
        raw = np.fromiter(map(call, get), np.float64, count).reshape(self.n, _N_READ)
        _command_batch(
            raw, forward, lateral, yaw_rate, altitude, self.has_response, self._queue, self._queue_len,
            self._time, self._delay, setpoints,
        )  # fmt: skip
        km = YAW_MOMENT_PER_THRUST_M * _LBFFT_PER_NM
        for k in range(self._steps):
            if k:
                raw = np.fromiter(map(call, get), np.float64, count).reshape(self.n, _N_READ)
            chunk = k // self._chunk if k % self._chunk == 0 else -1
            out = _physics_step(
                raw, setpoints, altitude, chunk, self.has_response, self.x, self.p, self._queue,
                self._queue_len, self._time, self._cmd, self._noisy, self._decay, self._kick, self._noise,
                self._drag, self._inner, self._h, self.memory, self.gains, self._armed, self._limit,
                self._lag, self.thrust, self._dt, km,
            )  # fmt: skip
            deque(map(call, put, out.tolist()), maxlen=0)  # consume: set every property, then
            deque(map(call, runs), maxlen=0)  # run every JSBSim instance one physics step
        for v, thrust, response in zip(
            self.vehicles, self.thrust.tolist(), self.has_response.tolist(), strict=True
        ):
            v._thrust = thrust
            if response:
                for _ in range(self._steps // self._chunk):
                    v._time += self._chunk * self._dt
            else:
                v._time += self._steps * self._dt
            v._state = v._read_state()


@njit(cache=True)
def _command_batch(
    raw, forward, lateral, yaw_rate, altitude, has_response, queue, queue_len, time, delay, setpoints
):  # pragma: no cover - compiled
    """Each vehicle's command at the start of a control period, rotated by its heading now.

    Ideal: ``Setpoint.from_body`` held for the whole period. Response: ``AutopilotResponse.command``
    (queued, due after the command delay).
    """
    nan = math.nan
    for i in range(raw.shape[0]):
        yaw = wrap_angle(math.pi / 2.0 - raw[i, 6])  # as Vehicle._read_state
        c, s = math.cos(yaw), math.sin(yaw)
        vx = forward[i] * c - lateral[i] * s
        vy = forward[i] * s + lateral[i] * c
        if has_response[i]:
            n = queue_len[i]
            if n == queue.shape[1]:
                raise ValueError("autopilot response command queue full")
            queue[i, n, 0] = time[i] + delay[i]
            queue[i, n, 1] = vx
            queue[i, n, 2] = vy
            queue[i, n, 3] = yaw_rate[i]
            queue_len[i] = n + 1
        else:
            sp = setpoints[i]
            sp[0], sp[1], sp[2], sp[3], sp[4], sp[5], sp[6], sp[7] = (
                vx,
                vy,
                nan,
                altitude[i],
                yaw_rate[i],
                nan,
                0.0,
                0.0,
            )


@njit(cache=True)
def _response_chunk(x, p, queue, queue_len, time, cmd, yaw, inner, h, i):  # pragma: no cover - compiled
    """``AutopilotResponse.setpoint``'s loop over its inner steps for vehicle ``i``: commands fall
    due on the same inner step, the model advances in the same runs."""
    done = 0
    while done < inner:
        todo = inner - done
        if queue_len[i] > 0:
            until_due = math.ceil((queue[i, 0, 0] - time[i]) / h - 1e-9)
            if until_due <= 1:
                cmd[i, 0], cmd[i, 1], cmd[i, 2] = queue[i, 0, 1], queue[i, 0, 2], queue[i, 0, 3]
                for q in range(queue_len[i] - 1):
                    queue[i, q] = queue[i, q + 1]
                queue_len[i] -= 1
                continue
            todo = min(todo, until_due - 1)
        _response_advance(x[i], p[i], cmd[i, 0], cmd[i, 1], cmd[i, 2], yaw, h, todo)
        time[i] += todo * h
        done += todo


@njit(cache=True)
def _physics_step(
    raw,
    setpoints,
    altitude,
    chunk,
    has_response,
    x,
    p,
    queue,
    queue_len,
    time,
    cmd,
    noisy,
    decay,
    kick,
    noise,
    drag,
    inner,
    h,
    memory,
    gains,
    armed,
    limit,
    lag,
    thrust,
    dt,
    km,
):  # pragma: no cover - compiled
    """One physics step of every vehicle: the response's setpoint on a chunk boundary, then
    ``Vehicle._advance``'s body (controller, thrust limit, motor lag); returns the 5 property
    values per vehicle (rotor thrusts in lbf, yaw moment in lbf ft), flat."""
    n = raw.shape[0]
    out = np.empty(n * 5)
    half_pi = 0.5 * math.pi
    nan = math.nan
    for i in range(n):
        r = raw[i]
        if chunk >= 0 and has_response[i]:
            if noisy[i]:
                x[i, _S_BX] = x[i, _S_BX] * decay[i] + kick[i] * noise[i, chunk, 0]
                x[i, _S_BY] = x[i, _S_BY] * decay[i] + kick[i] * noise[i, chunk, 1]
            yaw = wrap_angle(half_pi - r[6])
            x[i, _S_MX], x[i, _S_MY] = r[1] * _FT, r[2] * _FT  # as AutopilotResponse.setpoint
            _response_chunk(x, p, queue, queue_len, time, cmd, yaw, inner, h, i)
            sp = setpoints[i]
            sp[0], sp[1], sp[2], sp[3] = x[i, _S_VX], x[i, _S_VY], nan, altitude[i]
            sp[4], sp[5] = x[i, _S_R], nan
            sp[6] = x[i, _S_AX] - drag[i] * x[i, _S_VX]
            sp[7] = x[i, _S_AY] - drag[i] * x[i, _S_VY]
        c0 = c1 = c2 = c3 = 0.0
        if armed[i]:
            sp = setpoints[i]
            c0, c1, c2, c3 = control_step(
                memory[i],
                gains[i],
                sp[0],
                sp[1],
                sp[2],
                sp[3],
                sp[4],
                sp[5],
                sp[6],
                sp[7],
                dt,
                r[0] * _FT,
                r[1] * _FT,
                r[2] * _FT,
                -r[3] * _FT,
                r[4],
                -r[5],
                half_pi - r[6],
                r[7],
                -r[8],
                -r[9],
                r[10] != 0.0,
            )
            if limit[i]:
                t_max = MAX_ROTOR_THRUST_N
                c0, c1, c2, c3 = min(c0, t_max), min(c1, t_max), min(c2, t_max), min(c3, t_max)
        t = thrust[i]
        t[0] += lag[i] * (c0 - t[0])
        t[1] += lag[i] * (c1 - t[1])
        t[2] += lag[i] * (c2 - t[2])
        t[3] += lag[i] * (c3 - t[3])
        out[5 * i] = t[0] * _LBF_PER_N
        out[5 * i + 1] = t[1] * _LBF_PER_N
        out[5 * i + 2] = t[2] * _LBF_PER_N
        out[5 * i + 3] = t[3] * _LBF_PER_N
        out[5 * i + 4] = km * (t[2] + t[3] - t[0] - t[1])
    return out
