"""Shared fixtures: dtypes with their tolerances, the shared real data folder, a KITTI-like camera,
and the benchmark scripts as modules."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType
from typing import Callable, Iterator

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pytest_configure(config) -> None:
    """In each of pytest-xdist's processes, torch's intra-op threads are the process's share of
    the CPU's cores (one each where there are as many processes as cores), so that the
    processes' threads do not contend for the same cores."""
    import os

    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(workers)))


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request) -> torch.dtype:
    return request.param


@pytest.fixture
def device() -> torch.device:
    return torch.device("cpu")


def _load_benchmark(name: str) -> ModuleType:
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def load_benchmark() -> Callable[[str], ModuleType]:
    """``load_benchmark(name)``: ``benchmarks/<name>.py`` imported as a module (the folder is not a
    package)."""
    return _load_benchmark


def tolerance(dtype: torch.dtype) -> dict[str, float]:
    """assert_close tolerances per dtype."""
    return {torch.float32: dict(atol=1e-3, rtol=1e-4), torch.float64: dict(atol=1e-9, rtol=1e-9)}[dtype]


@pytest.fixture(scope="module")
def one_thread():
    """One intra-op thread for a module of many small tensor ops (fits, rendering): faster than two
    contending threads on a shared CPU; the previous count is restored afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)



@pytest.fixture
def no_hang() -> Iterator[None]:
    """The test fails with a TimeoutError rather than hanging where it waits more than 60 s (a job
    reading a FIFO that no one writes into): SIGALRM, on POSIX."""
    import signal

    def stop(signum, frame):
        raise TimeoutError("the test waited more than 60 s (on a FIFO that no one writes into?)")

    old = signal.signal(signal.SIGALRM, stop)
    signal.alarm(60)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


@pytest.fixture
def mount_table(monkeypatch) -> Callable[[str], None]:
    """``mount_table(text)``: the file system checks of ``fsof_torch.io.atomic`` read ``text`` as
    the process's mount table (``/proc/self/mountinfo``) for the rest of the test, or until
    ``monkeypatch.undo()``."""
    import io

    import fsof_torch.io.atomic as atomic

    real_open = open

    def use(text: str) -> None:
        monkeypatch.setattr(atomic, "open", lambda path, *a, **k: io.StringIO(text)
                            if path == "/proc/self/mountinfo" else real_open(path, *a, **k), raising=False)

    return use


@pytest.fixture
def kernel_paths(tmp_path_factory, mount_table) -> list[str]:
    """Paths on the kernel's proc and sysfs file systems, as a made-up mount table places them
    (two folders outside the test's ``tmp_path``; the same on any machine): outputs the jobs
    cannot create. The first is the proc file system's root itself, the others lie below one."""
    root = tmp_path_factory.mktemp("kernel")
    proc, sys_ = root / "proc", root / "sys"
    proc.mkdir()
    sys_.mkdir()
    mount_table("22 1 0:21 / / rw - ext4 /dev/vda rw\n"
                f"23 22 0:22 / {proc} rw,nosuid - proc proc rw\n"
                f"24 22 0:23 / {sys_} rw,nosuid - sysfs sysfs rw\n")
    return [str(proc), str(proc / "x"), str(sys_ / "x" / "y")]


@pytest.fixture
def interrupted(monkeypatch) -> Callable[[object, str, Callable[[], object]], None]:
    """``interrupted(owner, name, run)``: ``owner.name`` replaced by a function that raises
    KeyboardInterrupt (a run interrupted there), then ``run()``, which must stop with it: raise
    it, or, a job's ``main``, return the exit status 130 of an interrupted run."""
    calls = []

    def interrupt(*args, **kwargs):
        calls.append(1)
        raise KeyboardInterrupt

    def run_interrupted(owner: object, name: str, run: Callable[[], object]) -> None:
        monkeypatch.setattr(owner, name, interrupt)
        try:
            status = run()
        except KeyboardInterrupt:
            return
        assert calls and status == 130, f"expected the run interrupted in {name} (exit status 130), got {status!r}"

    return run_interrupted

@pytest.fixture(params=[
    ({"WORLD_SIZE": "2"}, "environment variable RANK: not set, while WORLD_SIZE is 2"),
    ({"WORLD_SIZE": "two"}, "environment variable WORLD_SIZE: expected a whole number from 1 up"),
    ({"WORLD_SIZE": "0"}, "environment variable WORLD_SIZE: expected a whole number from 1 up"),
    ({"WORLD_SIZE": "2", "RANK": "2"}, "environment variable RANK: expected a whole number from 0 to 1"),
    ({"WORLD_SIZE": "2", "RANK": "0", "LOCAL_RANK": "x"}, "environment variable LOCAL_RANK: expected"),
], ids=["no-rank", "size-two", "size-0", "rank-2", "local-rank-x"])
def torchrun_environment(request, monkeypatch) -> tuple[dict[str, str], str, str]:
    """torchrun's variables as torchrun never sets them (a WORLD_SIZE left in the shell, values
    that are no whole number in their range), with joining a process group a test failure:
    (the variables, the start of the job's message, what the message quotes: the value, or for
    a missing RANK the advice to start with torchrun)."""
    import torch.distributed as dist

    env, message = request.param
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    monkeypatch.setattr(dist, "init_process_group", lambda **kwargs: pytest.fail("joined a process group"))
    variable = message.split()[2].rstrip(":")
    return env, message, f"got {env[variable]!r}" if variable in env else "start the job with torchrun"


@pytest.fixture
def shared_data() -> Path:
    """The folder of real KITTI samples beside the project; tests using it skip when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture
def kitti15_ground_truth(shared_data):
    """The shared KITTI 2015 pair's ground truth: ``(camera, flow (1, 2, H, W) float64, valid
    (1, 1, H, W), road (1, 1, H, W))``, the camera 1.65 m high, road from road.json; skips when
    the pair is absent."""
    from fsof_torch import Camera
    from fsof_torch.io import read_kitti_flow, read_road_mask

    folder = shared_data / "kitti15_000000"
    if not folder.is_dir():
        pytest.skip("kitti15_000000 is absent")
    cam = Camera.from_kitti(folder / "calib_cam_to_cam.txt", cam=2, height=1.65)
    flow, valid = read_kitti_flow(folder / "flow_noc_10.png")
    road = read_road_mask(folder / "road.json", size=tuple(flow.shape[-2:]))
    return cam, flow[None].double(), valid[None], road[None]


@pytest.fixture
def kitti_K() -> torch.Tensor:
    return torch.tensor([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]],
                        dtype=torch.float64)


@pytest.fixture
def check_environment() -> Callable[..., None]:
    """``check_environment(env, job=..., command=..., seed=..., device="cpu")``: asserts that a JSON
    output's ``environment`` block (docs/jobs.md) names what produced it in this process: the
    command, the seed, the library's version and the digest of the library's and the job's code,
    the versions of Python, torch, OpenCV, kornia and NumPy, this machine's CPU count, the device."""
    def check(env: dict, *, job: str, command: str, seed: int | None, device: str = "cpu") -> None:
        import os
        import platform

        import cv2
        import kornia
        import numpy

        import fsof_torch
        from fsof_torch.io import code_digest, cpu_name

        job_folder = Path(__file__).resolve().parents[1] / job
        assert env["command"] == command and env["seed"] == seed
        assert isinstance(env["options"], dict)
        assert env["version"] == fsof_torch.__version__
        assert env["library_code"] == code_digest(job_folder) and env["code_packages"] == ["fsof_torch", job]
        assert env["dependencies"] == {"python": ".".join(platform.python_version_tuple()[:2]),
                                       "torch": torch.__version__, "opencv": cv2.__version__,
                                       "kornia": kornia.__version__, "numpy": numpy.__version__}
        assert env["python"] == platform.python_version() and env["platform"] == platform.platform()
        assert env["cpu"] == cpu_name() and env["cpu_count"] == os.cpu_count()
        assert set(env["threads"]) == {"torch", "opencv"} and env["threads"]["torch"] >= 1
        assert env["device"] == device and env["gpu"] is None and env["cuda"] == torch.version.cuda
    return check
