"""The Processing provider: the aerialmtl algorithms and the setting naming the ``aerialmtl`` program."""

from __future__ import annotations

from typing import Any

from processing.core.ProcessingConfig import ProcessingConfig, Setting
from qgis.core import QgsApplication, QgsProcessingProvider

from .algorithm import AerialMTLAlgorithm
from .spec import ALGORITHMS, EXECUTABLE_SETTING, default_executable


class AerialMTLProvider(QgsProcessingProvider):
    """Provider ``aerialmtl``: one algorithm per command (``aerialmtl:predict``, ``aerialmtl:buildings``, ...)."""

    def load(self) -> bool:
        """Register the executable setting (Settings → Options → Processing → Providers → aerialmtl)."""
        ProcessingConfig.settingIcons[self.name()] = self.icon()
        ProcessingConfig.addSetting(Setting(self.name(), EXECUTABLE_SETTING, "aerialmtl executable",
                                            default_executable(), valuetype=Setting.FILE))
        ProcessingConfig.readSettings()
        self.refreshAlgorithms()
        return True

    def unload(self) -> None:
        """Remove the setting."""
        ProcessingConfig.removeSetting(EXECUTABLE_SETTING)

    def loadAlgorithms(self) -> None:
        for spec in ALGORITHMS.values():
            self.addAlgorithm(AerialMTLAlgorithm(spec))

    def id(self) -> str:
        return "aerialmtl"

    def name(self) -> str:
        return "aerialmtl"

    def longName(self) -> str:
        return "aerialmtl: height and land cover with uncertainty from aerial orthophotos"

    def icon(self) -> Any:
        return QgsApplication.getThemeIcon("/processingAlgorithm.svg")
