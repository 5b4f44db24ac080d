"""n2d_common.ros.send_goal over real rclpy: a goal whose response never comes is sent again under a new id
(Fast DDS drops a goal response sent before the server matched the client), a goal the server took although its
response was lost is used rather than sent again, and no answer at all is a DeviceError that names the action.
JobActionServer keeps a cancel that comes between a goal's acceptance and its execution."""

import threading
import time
import uuid
from contextlib import contextmanager

import pytest
import rclpy
from action_msgs.msg import GoalStatus
from helpers import wait_future
from rclpy.action import ActionServer, GoalResponse
from rclpy.action.client import ClientGoalHandle
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from unique_identifier_msgs.msg import UUID

from n2d_common.errors import Cancelled, DeviceError
from n2d_common.ros import JobActionServer, SafeActionClient, background_node, send_goal
from n2d_interfaces.action import Rotate


class _Server:
    """A Rotate server in this process whose goal callback holds the first `silent` goals unanswered."""

    def __init__(self, silent: int):
        self.goals, self.silent, self.release = 0, silent, threading.Event()
        self.node = rclpy.create_node("test_send_goal_server")
        self.server = ActionServer(self.node, Rotate, "/test/rotate", execute_callback=self._execute,
                                   goal_callback=self._on_goal, callback_group=ReentrantCallbackGroup())
        self.executor = MultiThreadedExecutor(num_threads=4)
        self.executor.add_node(self.node)
        threading.Thread(target=self.executor.spin, daemon=True).start()

    def _on_goal(self, _goal):
        self.goals += 1
        if self.goals <= self.silent:
            self.release.wait()  # released only on close: refuse, so no goal is accepted while the server goes
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _execute(self, goal_handle):
        goal_handle.succeed()
        return Rotate.Result(success=True, angle_rad=goal_handle.request.angle_rad)

    def close(self) -> None:
        self.release.set()
        self.executor.shutdown(timeout_sec=5.0)
        self.server.destroy()
        self.node.destroy_node()


class _DeafClient(SafeActionClient):
    """Loses every goal response on arrival, as Fast DDS sometimes does without the server noticing (fault
    injection: the server and the transport are real)."""

    async def execute(self, taken_data):
        taken_data.pop("goal", None)
        return await super().execute(taken_data)


@contextmanager
def _client_and_server(ros_domain: int, silent: int, client_type=SafeActionClient):
    """An action client in a background node and a _Server holding its first `silent` goals unanswered."""
    with background_node("test_send_goal_client", ros_domain) as node:
        server = _Server(silent)
        try:
            client = client_type(node, Rotate, "/test/rotate")
            assert client.wait_for_server(timeout_sec=30)
            yield client, server
        finally:
            server.close()


@pytest.mark.timeout(60)
def test_a_goal_without_answer_is_sent_again(ros_domain):
    with _client_and_server(ros_domain, silent=1) as (client, server):
        goal = send_goal(client, Rotate.Goal(angle_rad=0.5), answer_s=1.0)
        assert goal.accepted and server.goals == 2
        result = wait_future(goal.get_result_async())
        assert result.status == GoalStatus.STATUS_SUCCEEDED and result.result.angle_rad == pytest.approx(0.5)


@pytest.mark.timeout(60)
def test_a_goal_taken_without_answer_is_not_sent_again(ros_domain):
    with _client_and_server(ros_domain, silent=0, client_type=_DeafClient) as (client, server):
        goal = send_goal(client, Rotate.Goal(angle_rad=0.25), answer_s=1.0)
        assert goal.accepted and server.goals == 1
        result = wait_future(goal.get_result_async())
        assert result.status == GoalStatus.STATUS_SUCCEEDED and result.result.angle_rad == pytest.approx(0.25)


@pytest.mark.timeout(60)
def test_no_answer_at_all_is_a_device_error(ros_domain):
    with _client_and_server(ros_domain, silent=10) as (client, server):
        with pytest.raises(DeviceError, match="turntable goal: no answer from /test/rotate within 2 s"):
            send_goal(client, Rotate.Goal(angle_rad=0.5), what="turntable", attempts=4, answer_s=0.5)
        assert server.goals == 4


class _PausableSpin:
    """Spins an executor in a thread that `paused()` holds between two spins."""

    def __init__(self, executor):
        self.executor, self.lock, self.stop = executor, threading.Lock(), threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self.stop.is_set():
            with self.lock:
                self.executor.spin_once(timeout_sec=0.02)

    @contextmanager
    def paused(self):
        with self.lock:
            yield

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5.0)


@pytest.mark.timeout(60)
def test_a_cancel_before_the_job_starts_cancels_it(ros_domain):
    """A goal and its cancel both wait at a JobActionServer that does not spin: rclpy then accepts the goal and
    cancels it in one pass, before the job starts. The job starts with its cancel event set, so it stops at once
    and the goal ends canceled (its cancel used to be cleared as the job started: it ran to the end). A first goal
    and a first cancel, both answered, make sure the server's goal and cancel readers are matched; the server spins
    on one thread, as with several an entity found ready by one wait may be taken after the next (20 of 20 runs
    pass; with the fix undone, 5 of 5 fail)."""
    with background_node("test_cancel_client", ros_domain) as node:
        server_node = rclpy.create_node("test_cancel_server")
        seen = []

        def run(_goal, _result, _progress, cancel: threading.Event) -> None:
            seen.append(cancel.is_set())
            if cancel.is_set():
                raise Cancelled("cancelled before the plate moved")

        jobs = JobActionServer(server_node, Rotate, "/test/jobs", run, accept=lambda _goal: True,
                               feedback=lambda _p: Rotate.Feedback())
        executor = SingleThreadedExecutor()  # a ready entity is taken and handled within its spin_once
        executor.add_node(server_node)
        spin = _PausableSpin(executor)
        try:
            client = SafeActionClient(node, Rotate, "/test/jobs")
            assert client.wait_for_server(timeout_sec=30)
            first = send_goal(client, Rotate.Goal(angle_rad=0.5))
            assert wait_future(first.get_result_async()).status == GoalStatus.STATUS_SUCCEEDED
            assert wait_future(_handle(client).cancel_goal_async()).goals_canceling == []  # an unknown goal
            with spin.paused():
                handle = _handle(client)
                client.send_goal_async(Rotate.Goal(angle_rad=1.0), goal_uuid=handle.goal_id)
                cancelled = handle.cancel_goal_async()
                time.sleep(1.0)  # goal and cancel reach the server's readers
            assert len(wait_future(cancelled).goals_canceling) == 1
            result = wait_future(handle.get_result_async())
            assert seen == [False, True] and jobs.state == "cancelled"
            assert result.status == GoalStatus.STATUS_CANCELED and "before the plate moved" in result.result.message
        finally:
            spin.close()
            executor.shutdown(timeout_sec=5.0)
            server_node.destroy_node()


def _handle(client) -> ClientGoalHandle:
    """A handle for a goal of a new id, as if the server had accepted it (to send its cancel before its goal is
    answered)."""
    goal_id = UUID(uuid=list(uuid.uuid4().bytes))
    return ClientGoalHandle(client, goal_id, Rotate.Impl.SendGoalService.Response(accepted=True))


@pytest.mark.timeout(60)
def test_a_job_that_stops_as_soon_as_it_is_cancelled_ends_canceled(ros_domain):
    """rclpy calls the cancel callback, which sets the job's cancel event, before it marks the goal CANCELING. A
    job that stops in that gap must still end its goal canceled, with a result the client receives (it used to
    end an EXECUTING goal as canceled, an invalid transition: the client waited for a result forever). The gap is
    widened here by a cancel callback that takes 0.3 s after setting the event (fault injection: server, client
    and transport are real)."""
    with background_node("test_cancel_gap_client", ros_domain) as node:
        server_node = rclpy.create_node("test_cancel_gap_server")

        def run(_goal, _result, _progress, cancel: threading.Event) -> None:
            cancel.wait(30)
            raise Cancelled("stopped at once")

        jobs = JobActionServer(server_node, Rotate, "/test/gap", run, accept=lambda _goal: True,
                               feedback=lambda _p: Rotate.Feedback())

        def slow_cancel(goal_handle):
            answer = jobs._on_cancel(goal_handle)
            time.sleep(0.3)  # the job thread runs to its end meanwhile
            return answer

        jobs._server.register_cancel_callback(slow_cancel)
        executor = MultiThreadedExecutor(num_threads=4)
        executor.add_node(server_node)
        threading.Thread(target=executor.spin, daemon=True).start()
        try:
            client = SafeActionClient(node, Rotate, "/test/gap")
            assert client.wait_for_server(timeout_sec=30)
            goal = send_goal(client, Rotate.Goal(angle_rad=0.5))
            time.sleep(0.5)
            assert len(wait_future(goal.cancel_goal_async()).goals_canceling) == 1
            result = wait_future(goal.get_result_async(), 20)
            assert result.status == GoalStatus.STATUS_CANCELED and "stopped at once" in result.result.message
        finally:
            executor.shutdown(timeout_sec=5.0)
            server_node.destroy_node()
