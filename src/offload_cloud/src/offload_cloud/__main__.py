"""`python -m offload_cloud`: the cloud server's command line, as `offload-cloud-server`."""
import sys

from offload_cloud.server_cli import main

sys.exit(main())
