"""Progressive imagery: JPEG 2000 (glymur / OpenJPEG) over a lossy acoustic link.

See ``docs/imagery.md``. The vehicle side (:class:`ImagerySender`) encodes each image, announces
it, sends it to a default set-point in capture order and serves operator goals first, with
selective acks and retransmission; the topside side (:class:`ImageryReceiver`) rebuilds the
JPEG 2000 header from a few parameter bits, decodes whole packets only (repairing around lost
fragments) and produces an improved image after every useful fragment. A region request is
answered with the region's packets or a crop (the region coded on its own, ``ImageCrop``),
which topside pastes over the image.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from coex import Modality
from coex.messages import (
    ImageAck,
    ImageAnnounce,
    ImageByTimeRequest,
    ImageCrop,
    ImageFragment,
    ImageGoal,
    ImageRegionRequest,
    ImageShortFragment,
    Message,
    TransferProgress,
)

from .codec import CodingParams, encode_image
from .product import CropProduct, ImageProduct, ProgressProduct
from .receiver import ImageryReceiver
from .sender import ImageInput, ImagerySender

__all__ = ["CodingParams", "CropProduct", "ImageInput", "ImageProduct", "ImageryModality", "ImageryReceiver",
           "ImagerySender", "ProgressProduct", "encode_image"]


class ImageryModality(Modality):
    """The ``imagery`` modality plugin."""

    name: ClassVar[str] = "imagery"
    version: ClassVar[str] = "1.0"
    messages: ClassVar[tuple[type[Message], ...]] = (ImageAnnounce, ImageFragment, TransferProgress, ImageCrop,
                                                     ImageShortFragment)
    requests: ClassVar[tuple[type[Message], ...]] = (ImageAck, ImageGoal, ImageByTimeRequest, ImageRegionRequest)
    #: acks of data: handled without expediting the stream
    routine: ClassVar[tuple[type[Message] | int, ...]] = (ImageAck,)

    def sender(self, config: Mapping[str, Any] | None = None) -> ImagerySender:
        return ImagerySender(config)

    def receiver(self, config: Mapping[str, Any] | None = None) -> ImageryReceiver:
        return ImageryReceiver(config)
