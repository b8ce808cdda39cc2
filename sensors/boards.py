"""Open the motor board a device spec names (:func:`sensors.motor_board.parse_device_spec`),
a real one or a built-in emulator; the caller gets a :class:`MotorBoard` and never the type."""

from __future__ import annotations

from typing import Any

from sensors.motor_board import MotorBoard, MotorBoardError, parse_device_spec


class OpenedBoard:
    """The board and, for ``emulator:KIND``, the emulator behind it (closed with it)."""

    def __init__(self, board: MotorBoard, emulator: Any = None) -> None:
        self.board, self.emulator = board, emulator

    def close(self) -> None:
        try:
            self.board.close()
        finally:
            if self.emulator is not None:
                self.emulator.close()

    def __enter__(self) -> MotorBoard:
        return self.board

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_board(spec: str, cfg: Any) -> OpenedBoard:
    """``cfg`` is the full :class:`rgbdnav.config.Config` (board, thunderborg, arduino_bridge,
    robot sections)."""
    dev = parse_device_spec(spec)
    if dev.kind == "eddie":
        from sensors.eddie import EddieBoard

        if dev.emulator:
            from sensors.eddie_emulator import EddieEmulator

            emu: Any = EddieEmulator(cfg.robot)
            try:
                return OpenedBoard(EddieBoard(emu.serve_pty(), cfg.board, cfg.robot), emu)
            except BaseException:
                emu.close()
                raise
        return OpenedBoard(EddieBoard(dev.path, cfg.board, cfg.robot))
    if dev.kind == "thunderborg":
        from sensors.thunderborg import ThunderBorgBoard

        tb = cfg.thunderborg
        if dev.emulator:
            from sensors.board_emulators import ThunderBorgEmulator

            emu = ThunderBorgEmulator(tb, cfg.robot)
            try:
                board = ThunderBorgBoard(
                    emu.bus(), emu.serve_tacho(), tb, cfg.board, cfg.robot, bus_name="emulated-i2c"
                )
            except BaseException:
                emu.close()
                raise
            return OpenedBoard(board, emu)
        try:
            from smbus2 import SMBus
        except ImportError:
            raise MotorBoardError("the ThunderBorg needs smbus2: pip install smbus2") from None
        bus_no = int(dev.path.rsplit("-", 1)[1])
        try:
            bus = SMBus(bus_no)
        except OSError as err:
            raise MotorBoardError(f"cannot open I2C bus {dev.path}: {err}") from err
        address = int(dev.option, 0) if dev.option else tb.address
        try:
            return OpenedBoard(
                ThunderBorgBoard(
                    bus,
                    dev.extra or tb.tacho_port,
                    tb,
                    cfg.board,
                    cfg.robot,
                    address=address,
                    bus_name=dev.path,
                )
            )
        except BaseException:
            bus.close()
            raise
    from sensors.arduino_bridge import ArduinoBridgeBoard

    br = cfg.arduino_bridge
    if dev.emulator:
        from sensors.board_emulators import BridgeEmulator

        emu = BridgeEmulator(br)
        try:
            return OpenedBoard(ArduinoBridgeBoard(emu.serve_pty(), br, cfg.board, cfg.robot), emu)
        except BaseException:
            emu.close()
            raise
    baud = int(dev.option) if dev.option else None
    return OpenedBoard(ArduinoBridgeBoard(dev.path, br, cfg.board, cfg.robot, baud))
