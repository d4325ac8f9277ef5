#!/usr/bin/env bash
# Regenerates emr_client/messages_pb2.py from proto/emr/v1/messages.proto with protoc (Debian's
# protobuf-compiler, as .ci/run installs it), then checks that it imports.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
out="$(mktemp -d)"
trap 'rm -rf "$out"' EXIT
protoc -I "$here/../../proto" --python_out="$out" emr/v1/messages.proto
cp "$out/emr/v1/messages_pb2.py" "$here/emr_client/messages_pb2.py"
PYTHONPATH="$here" python3 -c "import emr_client.messages_pb2"
echo "regenerated $here/emr_client/messages_pb2.py with $(protoc --version)"
