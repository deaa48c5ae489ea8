"""Managed (lifecycle) nodes: what a node does in each state of the ROS 2 node lifecycle design.

    unconfigured --configure--> inactive --activate--> active
                 <--cleanup---           <-deactivate-
    any primary state --shutdown--> finalized

A `ManagedNode` declares its parameters when constructed and nothing else.
`configure` loads and checks what a restart would be needed to change (the
checkpoint, read-only parameters) and creates its publishers, which stay
silent until `activate`; `activate` subscribes to its inputs, so an inactive
node does no work; `deactivate` unsubscribes and forgets half-received
frames; `cleanup` releases the model and publishers (back to unconfigured);
`shutdown` does whatever of that is still to do. A transition that fails
(bad checkpoint, bad parameter) logs why and leaves the node where it was;
one not valid from the current state (`activate` while active, an unknown
id or label), asked for by any participant over the ChangeState service, is
refused (the service answers false) with the reason logged: rclpy itself
raises there, which would end the process.

With the parameter `autostart` (default true) the node configures and
activates itself, so `ros2 run` works as for any node, and a failed
configure ends the process with the reason; `autostart:=false` leaves it
unconfigured for a lifecycle manager, `ros2 lifecycle set`, or the demo.
"""

from __future__ import annotations

from lifecycle_msgs.srv import ChangeState
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from co3sop_nodes.common.allocation import freeze_setup
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.ros.params import Param, Parameters

AUTOSTART = Param(
    "autostart",
    bool,
    "configure and activate on start; false: stay unconfigured until a lifecycle manager "
    "(or `ros2 lifecycle set`) drives the node",
    True,
)


class ManagedNode(LifecycleNode):
    """A lifecycle node whose transitions call `configure`, `activate`, `deactivate` and `release`
    (subclasses define them); a Co3sopError or OSError in one fails the transition with its reason logged."""

    def __init__(self, name: str, params: tuple[Param, ...]):
        super().__init__(name)
        self.params = Parameters(self, (*params, AUTOSTART))
        self.failure = ""  # the reason of the last failed transition
        self._configured = self._active = False
        service = self._service_change_state
        service.callback = self._guarded(service.callback)

    def _guarded(self, change_state):
        """The ChangeState service's callback, called only for a transition valid from the current state."""

        def callback(request: ChangeState.Request, response: ChangeState.Response) -> ChangeState.Response:
            machine = self._state_machine
            state = machine.current_state[1]
            valid = {label: tid for tid, label, *_ in machine.available_transitions}
            wanted = request.transition.label or request.transition.id
            if wanted not in (valid if request.transition.label else set(valid.values())):
                self.get_logger().warning(
                    f"lifecycle transition {wanted!r} refused: not valid from state {state!r} "
                    f"(valid: {', '.join(f'{label} ({tid})' for label, tid in valid.items()) or 'none'})"
                )
                response.success = False
                return response
            return change_state(request, response)

        return callback

    # --- what subclasses define ---

    def configure(self) -> None:
        """Load and check; create publishers. Raise Co3sopError with the reason to refuse."""

    def activate(self) -> None:
        """Subscribe to the inputs and start the timers."""

    def deactivate(self) -> None:
        """Undo `activate`."""

    def release(self) -> None:
        """Undo `configure`."""

    # --- the lifecycle callbacks ---

    def _run(self, step, what: str) -> TransitionCallbackReturn:
        try:
            step()
        except (Co3sopError, OSError) as exc:
            self.failure = f"{what} failed: {exc}"
            self.get_logger().error(self.failure)
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        result = self._run(self.configure, "configure")
        if result == TransitionCallbackReturn.SUCCESS:
            self._configured = True
            freeze_setup()  # the model and what configure built live until cleanup: out of the collector's walks
        else:
            self._run(self.release, "release after a failed configure")
        return result

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        super().on_activate(state)  # enables the lifecycle publishers
        result = self._run(self.activate, "activate")
        if result == TransitionCallbackReturn.SUCCESS:
            self._active = True
            self.get_logger().info("active")
        else:
            self._run(self.deactivate, "deactivate after a failed activate")
            super().on_deactivate(state)
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._active = False
        self.deactivate()
        self.get_logger().info("inactive")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._configured = False
        self.release()
        self.get_logger().info("unconfigured")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self._active:
            self._active = False
            self.deactivate()
        if self._configured:
            self._configured = False
            self.release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.on_shutdown(state)  # back to unconfigured with nothing held
        return TransitionCallbackReturn.SUCCESS

    def start(self) -> ManagedNode:
        """Configure and activate when `autostart` says so; a failure raises Co3sopError with its reason."""
        if self.params["autostart"]:
            for trigger in (self.trigger_configure, self.trigger_activate):
                if trigger() != TransitionCallbackReturn.SUCCESS:
                    raise Co3sopError(self.failure or "lifecycle transition failed")
        return self
