"""The HTTP API's path parameters, with the id rules in the schema."""
from __future__ import annotations

from typing import Annotated

from fastapi import Path as PathParam

__all__ = ["VolumeId", "JobId"]

# the id rules in the schema, so that generated clients and schemathesis send ids the server takes; checked by the
# routes themselves (check_volume_id: 400 naming the id; a job id that is not one: 404)
VolumeId = Annotated[str, PathParam(description="volume id: the store's folder name under the root (a letter or "
                                                "digit, then up to 127 letters, digits, '.', '_' or '-')",
                                    json_schema_extra={"pattern": "^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$",
                                                       "minLength": 1, "maxLength": 128})]
JobId = Annotated[str, PathParam(description="job id (32 hex digits)", max_length=200,
                                 json_schema_extra={"pattern": "^[0-9a-f]{32}$", "minLength": 32, "maxLength": 32})]
