"""Entry point object for the ``edygs-data`` dataparser (pyproject: nerfstudio.dataparser_configs).

This module is loaded while nerfstudio builds its dataparser registry, so it imports only the
dataparser, never a datamanager (full_images_datamanager imports that registry: a cycle).
"""

from __future__ import annotations

from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from edygs_ns.data.dataparser import EdygsDataParserConfig

edygs_dataparser = DataParserSpecification(
    config=EdygsDataParserConfig(),
    description="EDyGS scenes: blurry frames + events (processed layout, E2NeRF synthetic and real, EvDeblurNeRF)",
)
