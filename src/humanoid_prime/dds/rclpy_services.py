"""The services of the rclpy node (``rclpy_node.py``): ``~/switch_mode`` and ``~/reset_faults`` (prime_msgs),
answered once the loop has applied them, as ``prime switch`` and ``prime reset`` are, and the controller manager's
``list_controllers`` and ``switch_controller`` under ``/controller_manager``, where ``ros2 control`` looks
(``controllers.py``). Every one answers, even when its handler fails (the failure is flagged and said), and what
would switch a mode or reset a fault is refused without ``--dds-control``."""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Protocol, TypeVar

from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node

from humanoid_prime.control.flags import Level, SafetyFlags
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.dds.controllers import (
    NAMESPACE,
    Switch,
    SwitchRefused,
    SwitchResult,
    controllers,
    mode_to_activate,
)
from humanoid_prime.dds.domain import in_namespace
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode

STRICT = 2  # controller_manager_msgs/SwitchController's strictness: refuse a request that cannot be done as asked
DEFAULT_WAIT_S = 2.0  # how long a service waits for the loop to apply a switch or reset when not told
NOT_CONTROLLING = "this run takes no commands from the ROS 2 graph (start Prime with --dds-control)"

R = TypeVar("R")
S = TypeVar("S")


# The fields Prime reads and writes of the ROS 2 messages it serves (rclpy's generated classes, untyped).
class Duration(Protocol):
    sec: int
    nanosec: int


class _SwitchModeRequest(Protocol):
    mode: str
    timeout: float


class _SwitchModeResponse(Protocol):
    success: bool
    outcome: str
    active_mode: str
    message: str


class _ResetFaultsResponse(Protocol):
    success: bool
    faults: list[str]
    message: str


class _ListControllersResponse(Protocol):
    controller: list[object]


class _SwitchControllerRequest(Protocol):
    activate_controllers: Sequence[str]
    deactivate_controllers: Sequence[str]
    strictness: int
    timeout: Duration


class _SwitchControllerResponse(Protocol):
    ok: bool
    message: str


def seconds(duration: Duration) -> float:
    return float(duration.sec + duration.nanosec * 1e-9)


def interface(name: str) -> ModuleType | None:
    """``pkg.msg`` (or ``.srv``, ``.action``), or None where the package is not installed."""
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


class ModeServices(SafetyFlags):
    """The node's services; mixed into the node, whose attributes below they use."""

    node: Node
    namespace: str
    manager: ControllerManager
    control: bool
    switch: Switch | None
    missing: list[str]
    _group: ReentrantCallbackGroup

    def _log(self, text: str, level: Level | None, outer: bool = True) -> None:
        raise NotImplementedError

    def _guarded(self, name: str, handler: Callable[[R, S], S]) -> Callable[[R, S], S]:
        """``handler``, answering even when it fails (an exception would leave the caller waiting forever): the
        failure is flagged and said in the answer's ``message``."""

        def answer(request: R, response: S) -> S:
            try:
                return handler(request, response)
            except Exception as exc:  # noqa: BLE001 - said in the answer and on /safety_status
                text = f"{name} failed: {type(exc).__name__}: {exc}"
                self.set_flag("service", text, Level.WARN)
                if hasattr(response, "message"):
                    response.message = text
                return response

        return answer

    def _services(self) -> None:
        """Serve what the installed interfaces allow (the start-up line names what is left out)."""
        prime = interface("prime_msgs.srv")
        if prime is None:
            self.missing.append("prime_msgs (~/switch_mode, ~/reset_faults left out)")
        else:
            self.node.create_service(prime.SwitchMode, "~/switch_mode",
                                     self._guarded("~/switch_mode", self._switch_mode), callback_group=self._group)
            self.node.create_service(prime.ResetFaults, "~/reset_faults",
                                     self._guarded("~/reset_faults", self._reset_faults), callback_group=self._group)
        cm = interface("controller_manager_msgs.srv")
        if cm is None:
            self.missing.append("controller_manager_msgs (the controller manager's services left out)")
        else:
            self._cm_msg = importlib.import_module("controller_manager_msgs.msg")
            where = in_namespace(self.namespace, NAMESPACE)
            self.node.create_service(cm.ListControllers, f"{where}/list_controllers",
                                     self._guarded("list_controllers", self._list_controllers),
                                     callback_group=self._group)
            self.node.create_service(cm.SwitchController, f"{where}/switch_controller",
                                     self._guarded("switch_controller", self._switch_controller),
                                     callback_group=self._group)

    def _switch(self, mode: Mode, wait_s: float) -> SwitchResult:
        if not self.control:
            return SwitchResult("refused", "", f"{mode.value} refused: {NOT_CONTROLLING}")
        if self.switch is None:
            return SwitchResult("refused", "", f"{mode.value} refused: this run switches no modes")
        try:
            return self.switch(mode, wait_s if wait_s > 0 else DEFAULT_WAIT_S)
        except PrimeError as exc:
            return SwitchResult("refused", "", str(exc))

    def _switch_mode(self, request: _SwitchModeRequest, response: _SwitchModeResponse) -> _SwitchModeResponse:
        try:
            answer = self._switch(Mode.parse(request.mode), request.timeout)
        except ValueError as exc:
            answer = SwitchResult("refused", "", str(exc))
        response.success, response.outcome = answer.ok, answer.outcome
        response.active_mode, response.message = answer.active, answer.message
        self._log(f"~/switch_mode: {answer.message}", None if answer.ok else Level.WARN)
        return response

    def _reset_faults(self, request: object, response: _ResetFaultsResponse) -> _ResetFaultsResponse:
        if not self.control:
            response.success, response.message = False, NOT_CONTROLLING
            return response
        before = self.manager.resets
        faults = self.manager.request_reset()
        deadline = time.monotonic() + DEFAULT_WAIT_S
        while self.manager.resets == before and time.monotonic() < deadline:
            time.sleep(self.manager.period / 2)
        applied = self.manager.resets != before
        response.success = applied
        response.faults = list(faults)
        response.message = (f"reset applied; {len(faults)} latched fault(s) before it" if applied else
                            f"the control loop did not apply the reset within {DEFAULT_WAIT_S:g} s")
        self._log(f"~/reset_faults: {response.message}", None if applied else Level.WARN)
        return response

    def _list_controllers(self, request: object, response: _ListControllersResponse) -> _ListControllersResponse:
        states: list[object] = []
        for info in controllers(self.manager):
            state = self._cm_msg.ControllerState()
            state.name, state.state, state.type, state.update_rate = info.name, info.state, info.type, info.update_rate
            state.claimed_interfaces = list(info.claimed_interfaces)
            state.required_command_interfaces = list(info.required_command_interfaces)
            state.required_state_interfaces = list(info.required_state_interfaces)
            states.append(state)
        response.controller = states
        return response

    def _switch_controller(self, request: _SwitchControllerRequest,
                           response: _SwitchControllerResponse) -> _SwitchControllerResponse:
        strict = request.strictness == STRICT
        try:
            mode = mode_to_activate(self.manager, list(request.activate_controllers),
                                    list(request.deactivate_controllers), strict)
        except SwitchRefused as exc:
            response.ok, response.message = False, str(exc)
        else:
            if mode is None:
                response.ok, response.message = True, "nothing to switch"
            else:
                answer = self._switch(mode, seconds(request.timeout))
                response.ok, response.message = answer.ok, answer.message
        self._log(f"switch_controller: {response.message}", None if response.ok else Level.WARN)
        return response
