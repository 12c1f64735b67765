"""Decode every message of an MCAP recording against its channel's schema with the mcap library:
JSON channels (``jsonschema`` schemas) with ``jsonschema.validate``, protobuf channels (Foxglove's
well-known schemas) with ``mcap_protobuf``'s decoder built from the schema's FileDescriptorSet.
Returns {topic: {"schema", "encoding", "messages"}}; raises on the first message that fails."""
from __future__ import annotations

import json
from pathlib import Path


def decode_all(path: str | Path) -> dict:
    import jsonschema
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out: dict = {}
    validators: dict = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "json":
                v = validators.get(schema.id)
                if v is None:
                    s = json.loads(schema.data)
                    jsonschema.Draft202012Validator.check_schema(s)
                    v = validators[schema.id] = jsonschema.Draft202012Validator(s)
                v.validate(json.loads(message.data))
            elif channel.message_encoding == "protobuf":
                decoded = reader.decoder(schema, channel) if hasattr(reader, "decoder") else None
                if decoded is None:
                    decoded = DecoderFactory().decoder_for(channel.message_encoding, schema)
                obj = decoded(message.data)
                assert type(obj).DESCRIPTOR.full_name == schema.name
            else:
                raise AssertionError(f"{channel.topic}: unexpected encoding {channel.message_encoding}")
            t = out.setdefault(channel.topic, {"schema": schema.name, "encoding": channel.message_encoding,
                                               "messages": 0})
            t["messages"] += 1
    return out
