"""Every maneuver step ``dbw calibrate`` knows, by its command name."""

from __future__ import annotations

from appliance.maneuvers.k_ratio_step import KRatioStep
from appliance.maneuvers.lookahead_step import LookaheadStep
from appliance.maneuvers.palm_tree_step import PalmTreeStep
from appliance.maneuvers.pedals_step import PedalsStep
from appliance.maneuvers.pot_map_step import PotMapStep
from appliance.maneuvers.steps import HandStep, PotCentreStep

STEP_CLASSES: dict[str, type[HandStep]] = {
    PotCentreStep.name: PotCentreStep,
    PotMapStep.name: PotMapStep,
    PalmTreeStep.name: PalmTreeStep,
    KRatioStep.name: KRatioStep,
    LookaheadStep.name: LookaheadStep,
    PedalsStep.name: PedalsStep,
}
