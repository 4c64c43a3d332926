"""A local S3-compatible server for tests (moto). Starts on a free loopback port, creates
the buckets named on the command line, prints `PORT <n>`, and serves until stdin closes.
Exit 77: moto is not installed."""
import sys

try:
    import boto3
    from moto.server import ThreadedMotoServer
except ImportError as e:  # pragma: no cover
    print(f"moto[server] not installed: {e}", file=sys.stderr)
    sys.exit(77)

server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
server.start()
host, port = server.get_host_and_port()
s3 = boto3.client(
    "s3",
    endpoint_url=f"http://{host}:{port}",
    aws_access_key_id="test",
    aws_secret_access_key="test",
    region_name="us-east-1",
)
for bucket in sys.argv[1:]:
    s3.create_bucket(Bucket=bucket)
print(f"PORT {port}", flush=True)
sys.stdin.read()
server.stop()
