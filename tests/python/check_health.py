"""Asks a server's standard gRPC health service (grpc.health.v1), in plaintext, for its
overall status and the coordinator's (or the services named after the address) with
Python's grpcio, an implementation independent of ours. Exit 77: grpcio missing."""
import sys

try:
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc
except ImportError as e:  # pragma: no cover
    print(f"grpcio-health-checking not installed: {e}", file=sys.stderr)
    sys.exit(77)

addr = sys.argv[1]
# The services to ask for ("" is the server as a whole); default: the coordinator's.
services = sys.argv[2:] or ["", "osrt.v1.Coordinator"]
with grpc.insecure_channel(addr) as channel:
    grpc.channel_ready_future(channel).result(timeout=20)
    stub = health_pb2_grpc.HealthStub(channel)
    for service in services:
        reply = stub.Check(health_pb2.HealthCheckRequest(service=service), timeout=10)
        status = health_pb2.HealthCheckResponse.ServingStatus.Name(reply.status)
        print(f"{service or '(server)'}: {status}")
        if status != "SERVING":
            sys.exit(1)
