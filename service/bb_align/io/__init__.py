"""Files in and out: point clouds and box files (``clouds``), OPV2V / V2V4Real datasets (``dataset``), the
diagnostic alignment figure (``plot``)."""
