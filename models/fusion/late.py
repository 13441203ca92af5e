"""Late fusion: every agent detects in its own frame; boxes meet in the ego frame for NMS."""
from __future__ import annotations

import torch

from models.box_coder import AnchorBoxCoder
from models.fusion.base import BYTES_PER_BOX, FusionModule, _check, transform_boxes


class LateFusion(FusionModule):
    """Late fusion: every agent detects in its own frame; boxes meet in the ego frame for NMS."""

    def forward(self, pillars: dict, *, agent_mask: torch.Tensor, transforms=None, time_delay=None,
                agent_types=None) -> dict[str, torch.Tensor]:
        """Head dicts of the present agents, (V, ...) with V = agent_mask.sum() in b-major order;
        train them with each agent's own labels (OpenCOOD's LateFusionDataset)."""
        agent_mask = _check(agent_mask)
        b, l = agent_mask.shape
        d = self.detector
        return d.head(d.backbone(d.bev(pillars, b * l, keep=agent_mask.flatten())))

    def detections(self, output, coder, *, agent_mask, transforms, score_threshold, max_boxes):
        return self.boxes_in_ego(output, coder, agent_mask=agent_mask, transforms=transforms,
                                 score_threshold=score_threshold, max_boxes_per_agent=max_boxes)

    def message_bytes(self, *, points: float, boxes: float) -> float:
        return float(boxes * BYTES_PER_BOX)

    @staticmethod
    def boxes_in_ego(output: dict[str, torch.Tensor], box_coder: AnchorBoxCoder, *, agent_mask: torch.Tensor,
                     transforms, score_threshold: float = 0.2,
                     max_boxes_per_agent: int | None = None) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per sample: every present agent's decoded boxes (score > threshold) moved into the ego
        frame in float64 and concatenated -> (boxes (K, 7) float64, scores (K,)), before NMS."""
        agent_mask = _check(agent_mask)
        b, l = agent_mask.shape
        t = torch.as_tensor(transforms, dtype=torch.float64).reshape(b * l, 4, 4)
        slots = agent_mask.flatten().nonzero()[:, 0].tolist()
        per_agent = box_coder.decode_predictions(output, score_threshold=score_threshold, max_boxes=max_boxes_per_agent)
        merged: list[list] = [[] for _ in range(b)]
        for slot, (boxes, scores) in zip(slots, per_agent):
            merged[slot // l].append((transform_boxes(boxes, t[slot].to(boxes.device)), scores))
        return [(torch.cat([m[0] for m in ms]), torch.cat([m[1] for m in ms])) for ms in merged]
