"""Lab devices: the camera and coil-driver interfaces (:mod:`.base`), the contract every adapter keeps
(:mod:`.contract`) and the shipped adapters."""
