"""The vehicle side as a program: ``coex vehicle --config vehicle.toml`` (and ``coex topside
--config``, ``coex config check``). Inputs from the vehicle's own middleware
(:mod:`.inputs`, entry-point group ``coex.inputs``) feed the modality senders; accepted survey
commands go to the vehicle's autonomy (:mod:`.autonomy`, group ``coex.autonomy``)."""
