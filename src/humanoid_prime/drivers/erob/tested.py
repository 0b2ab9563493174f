"""The eRob that Prime has been tested with: firmware revisions and the rated torque (0x6076) of each model.

``prime doctor`` compares every drive on the ring with these tables. A drive outside them is not known to be
wrong, only not known to be right: bring it up with care, then add it here (one line, with its source).
"""

from __future__ import annotations

from dataclasses import dataclass

# Revision number (SII word 0x0C, 0x1018:03) -> where it is documented. The eRob's EtherCAT identity as IgH's
# `ethercat cstruct` prints it for a "ZeroErr Driver": vendor 0x5A65726F, product 0x00029252, revision 0x00000001
# (public dumps of eRob rings); the emulated eRob presents the same.
TESTED_REVISIONS: dict[int, str] = {
    0x00000001: "ZeroErr eRob EtherCAT (IgH `ethercat cstruct` of a ZeroErr Driver)",
}


@dataclass(frozen=True)
class ErobModel:
    """One eRob model: the rated torque its drive reports (0x6076), and where known the motor Kt and gear that the
    hardware file gives such a joint (``joints.erob_kt``, ``joints.erob_gear``)."""

    name: str
    rated_torque_nm: float
    source: str
    kt_nm_per_mA: float | None = None
    gear: float | None = None


# 0x6076 is UNSIGNED32 mN*m. Kt from the eRob manual's motor torque constants (DESIGN §2).
EROB_MODELS: tuple[ErobModel, ...] = (
    ErobModel("eRob70 50:1", 23.0, "nominal eRob70 50:1 figure (drivers/erob/constants.py)", 0.132e-3, 50.0),
    ErobModel("eRob80H120I", 31.0, "0x6076 read off an eRob80H120I (DESIGN §2)"),
)
RATED_TORQUE_TOLERANCE = 0.02  # of the rated torque: a drive reports its model's catalogue figure, not a measurement


def model_for(kt_nm_per_mA: float, gear: float) -> ErobModel | None:
    """The tested model with this Kt (to 0.1 %) and gear, if any."""
    for model in EROB_MODELS:
        if model.kt_nm_per_mA is None or model.gear is None:
            continue
        if abs(model.kt_nm_per_mA - kt_nm_per_mA) <= 1e-3 * model.kt_nm_per_mA and abs(model.gear - gear) < 1e-6:
            return model
    return None


def model_reading(rated_torque_nm: float) -> ErobModel | None:
    """The tested model whose drive reports this rated torque, if any."""
    for model in EROB_MODELS:
        if abs(rated_torque_nm - model.rated_torque_nm) <= RATED_TORQUE_TOLERANCE * model.rated_torque_nm:
            return model
    return None
