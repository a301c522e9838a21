"""Simulated LabJack T7, in the pieces ophyd-async splits its simulated detector into: the register map
(:mod:`.registers`), plant coupling and analog channels (:mod:`.coupling`, :mod:`.analog`), the stream engine
(:mod:`.stream_in`), stream-out (:mod:`.stream_out`), the watchdog (:mod:`.watchdog`), MBFB (:mod:`.feedback`), the
register dispatch (:mod:`.register_io`), composed and served by :class:`~sim_devices.t7.device.LabJackT7Sim`
(:mod:`.device`).

Sources are tagged [D] datasheet / register map (``ljm_constants.json``), [E] LabJack's low-level stream example,
[A] assumed, [L] twin limitation; each module lists its own.
"""
