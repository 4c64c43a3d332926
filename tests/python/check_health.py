"""Asks a server's standard gRPC health service (grpc.health.v1) for its overall status
with Python's grpcio, an implementation independent of ours. Exit 77: grpcio missing."""
import sys

try:
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc
except ImportError as e:  # pragma: no cover
    print(f"grpcio-health-checking not installed: {e}", file=sys.stderr)
    sys.exit(77)

addr = sys.argv[1]
with grpc.insecure_channel(addr) as channel:
    grpc.channel_ready_future(channel).result(timeout=20)
    stub = health_pb2_grpc.HealthStub(channel)
    for service in ["", "osrt.v1.Coordinator"]:
        reply = stub.Check(health_pb2.HealthCheckRequest(service=service), timeout=10)
        status = health_pb2.HealthCheckResponse.ServingStatus.Name(reply.status)
        print(f"{service or '(server)'}: {status}")
        if status != "SERVING":
            sys.exit(1)
