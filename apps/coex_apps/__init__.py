"""The CoEx applications: the topside console (:mod:`.console`), the vehicle daemon
(:mod:`.vehicle`) and the demo (:mod:`.demo`); each adds its sub-commands to ``coex`` through the
``coex.commands`` entry points. They sit above the plugins and import them; nothing imports them."""
