"""The composition root: hardware components built by block name, the run session, the control socket,
signals and the eRob impedance manager."""
