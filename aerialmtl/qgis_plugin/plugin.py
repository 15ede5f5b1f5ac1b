"""The plugin object QGIS loads: it registers the Processing provider."""

from __future__ import annotations

from typing import Any

from qgis.core import QgsApplication

from .provider import AerialMTLProvider


class AerialMTLPlugin:
    """Adds the aerialmtl algorithms to the Processing toolbox (and to ``qgis_process``)."""

    def __init__(self, iface: Any) -> None:
        self.iface = iface
        self.provider: AerialMTLProvider | None = None

    def initProcessing(self) -> None:  # the name QGIS calls (also without a GUI)
        """Register the provider."""
        self.provider = AerialMTLProvider()
        QgsApplication.processingRegistry().addProvider(self.provider)

    def initGui(self) -> None:
        """Called by QGIS when the plugin is loaded with a GUI."""
        self.initProcessing()

    def unload(self) -> None:
        """Remove the provider."""
        if self.provider is not None:
            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None
