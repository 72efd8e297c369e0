import threading

import numpy as np
import pytest

from mf_lpr_ros.core import workers as workers_module
from mf_lpr_ros.core.workers import Workers


def test_run_hands_each_worker_number_to_its_own_thread():
    seen = {}
    barrier = threading.Barrier(2, timeout=10)

    def work(worker: int) -> None:
        barrier.wait()  # both workers can only pass together: on two threads
        seen[worker] = threading.get_ident()

    Workers(2).run(work)
    assert sorted(seen) == [0, 1]
    assert len(set(seen.values())) == 2


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_each_gives_every_tasks_result_in_order_two_threads_running_side_by_side(threads):
    barrier = threading.Barrier(2, timeout=10)

    def task(index: int):
        if threads == 2 and index < 2:
            barrier.wait()  # the first two tasks can only pass together: on two threads
        return index, threading.get_ident()

    results = Workers(threads).each(*(lambda index=index: task(index) for index in range(5)))
    assert [index for index, _ in results] == [0, 1, 2, 3, 4]
    if threads == 1:
        assert {ident for _, ident in results} == {threading.get_ident()}
    if threads == 2:
        assert results[0][1] == results[2][1] == threading.get_ident() != results[1][1]


def test_run_reraises_a_workers_error():
    def fail_on_the_second(worker: int) -> None:
        if worker == 1:
            raise ValueError("worker 1 failed")

    with pytest.raises(ValueError, match="worker 1 failed"):
        Workers(2).run(fail_on_the_second)


# Split by columns (2-D; a stack one operand lacks; a stack of one) and by whole matrices.
@pytest.mark.parametrize("shapes", [((21, 74), (74, 30000)), ((63, 60), (37, 60, 900)),
                                    ((1, 630, 600), (1, 600, 900)),
                                    ((37, 63, 60), (37, 60, 900)), ((3, 630, 60), (3, 60, 901))])
def test_a_split_product_equals_the_whole(shapes):
    rng = np.random.default_rng(0)
    left, right = (rng.normal(size=shape).astype(np.float32) for shape in shapes)
    split = Workers(2).matmul(left, right)
    np.testing.assert_allclose(split, left @ right, rtol=1e-5, atol=1e-4)


def test_blas_is_held_to_one_thread_only_while_a_threaded_search_runs():
    controller = workers_module._blas_controller()
    before = [info["num_threads"] for info in controller.info() if info["user_api"] == "blas"]
    with Workers(2).own_cores():
        inside = [info["num_threads"] for info in workers_module._blas_controller().select(
            user_api="blas").info()]
    assert inside and all(count == 1 for count in inside)
    after = [info["num_threads"] for info in controller.info() if info["user_api"] == "blas"]
    assert after == before


def test_without_threadpoolctl_a_search_stays_on_one_thread(monkeypatch):
    monkeypatch.setattr(workers_module, "available", lambda module: False)
    assert Workers(4).threads == 1


def test_work_handed_out_from_a_worker_runs_there_instead_of_waiting_for_itself():
    workers = Workers(2)
    done = []

    def outer(worker: int) -> None:
        workers.run(lambda inner: done.append((worker, inner)))

    workers.run(outer)
    assert sorted(done) == [(0, 0), (0, 1), (1, 0), (1, 1)]


def test_overlapping_threaded_searches_give_back_the_limits_found_before_them():
    controller = workers_module._blas_controller()
    before = [info["num_threads"] for info in controller.info() if info["user_api"] == "blas"]
    first, second = Workers(2).own_cores(), Workers(2).own_cores()
    first.__enter__()
    second.__enter__()
    first.__exit__(None, None, None)
    still_held = [info["num_threads"] for info in controller.info()
                  if info["user_api"] == "blas"]
    second.__exit__(None, None, None)
    after = [info["num_threads"] for info in controller.info() if info["user_api"] == "blas"]
    assert all(count == 1 for count in still_held)
    assert after == before
