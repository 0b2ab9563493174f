"""Types of the compiled eRob tick (_tick.pyx): what the checker sees of it."""

import numpy as np
import numpy.typing as npt

_Floats = npt.NDArray[np.float64]
_Bytes = npt.NDArray[np.uint8]
_Layout = tuple[tuple[tuple[str, int], ...], int]

def layouts() -> dict[str, _Layout]: ...

class EcTick:
    grace_ticks: int
    def __init__(self, inputs: npt.NDArray[np.void], outputs: npt.NDArray[np.void], rec: npt.NDArray[np.void],
                 ring: npt.NDArray[np.intp], index: npt.NDArray[np.intp], raw: _Floats, state_factor: _Floats,
                 state_offset: _Floats, command_factor: _Floats, command_offset: _Floats, held: _Floats,
                 enabled: _Bytes, fault: _Bytes, state: _Bytes, chart: _Bytes, states: tuple[int, int, int],
                 cw_table: npt.NDArray[np.uint16], cw_prev: npt.NDArray[np.uint16],
                 enabled_pattern: tuple[int, int], fault_pattern: tuple[int, int], fault_reset: int,
                 disable_voltage: int, mode: int, target_limits: tuple[float, float],
                 velocity_limits: tuple[float, float], torque_limits: tuple[float, float],
                 grace: npt.NDArray[np.uint16]) -> None: ...
    def gather(self) -> int: ...
    def read(self, state: _Floats) -> tuple[int, bool]: ...
    def controlwords(self, reset: _Bytes | None = None) -> None: ...
    def write(self, command: _Floats, reset: _Bytes | None = None) -> None: ...
