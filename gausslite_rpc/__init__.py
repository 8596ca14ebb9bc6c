"""Generated gRPC/protobuf code of ``proto/gausslite_rpc``. Do not edit: run
``python scripts/gen_proto.py``; ``--check`` verifies it is current."""
