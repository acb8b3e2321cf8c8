"""The robot bench reads its driver's output: a traceback there fails the run, but for the
interpreter's note on an rclpy Task that SIGTERM interrupted at exit."""


def test_the_robot_bench_ignores_only_rclpys_note_on_a_task_interrupted_at_exit():
    from area3d_bench.robot import _RCLPY_TASK_FINALISER

    note = (
        "Exception ignored in: <function Future.__del__ at 0x7f9a689b7380>\n"
        "Traceback (most recent call last):\n"
        '  File "rclpy/task.py", line 56, in __del__\n'
        "    if self._exception is not None and not self._exception_fetched:\n"
        "AttributeError: 'Task' object has no attribute '_exception'\n"
    )
    report = '{"frames_published": 148}\n'
    assert _RCLPY_TASK_FINALISER.sub("", note + report) == report
    failure = 'Traceback (most recent call last):\n  File "d.py", line 1\nValueError: boom\n'
    assert "Traceback" in _RCLPY_TASK_FINALISER.sub("", note + failure)
