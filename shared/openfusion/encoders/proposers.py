"""The region proposer of the CLIP encoders (``clip-regions``, ``clip-dense``), chosen in one place:
an ONNX ``mask-proposer`` when a mask model is given, else graph segmentation on color + depth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from openfusion.encoders.proposal_encoder import RegionProposer


def make_proposer(mask_model_path: str | Path | None, proposer_options: dict[str, Any] | None,
                  *, device: str) -> RegionProposer:
    """The proposer of the CLIP encoders: an ONNX ``mask-proposer`` (``mask_model_path``) or graph
    segmentation on color + depth; ``proposer_options`` go to whichever is used."""
    if mask_model_path is not None:
        from openfusion.encoders.onnx_backend import OnnxMaskProposer
        from openfusion.encoders.onnx_contract import load_onnx_model

        mask_model = load_onnx_model(mask_model_path, expected_kind="mask-proposer", device=device)
        return OnnxMaskProposer(mask_model, **(proposer_options or {}))
    from openfusion.encoders.graph_segmentation import GraphSegmentationProposer

    return GraphSegmentationProposer(**(proposer_options or {}))
