"""The tests' InfluxDB is the real server and speaks what influxdb-client speaks: a point
written through the v2 write API to ``bench/autogen`` comes back from a Flux query, and
the server survives a stop and a start with its data."""

from __future__ import annotations

import pytest
from influxdb_client import InfluxDBClient
from influxdb_client.client.write_api import SYNCHRONOUS
from influxrig import InfluxServer

pytestmark = pytest.mark.integration


def _flux_values(server: InfluxServer, measurement: str) -> list[float]:
    with InfluxDBClient(url=server.url, token=server.token, org=server.org) as client:
        tables = client.query_api().query(
            f'from(bucket: "{server.bucket}") |> range(start: 0)'
            f' |> filter(fn: (r) => r._measurement == "{measurement}")'
        )
    return [float(r.get_value()) for t in tables for r in t.records]


def test_a_line_written_with_influxdb_client_is_read_back_with_flux(influx: InfluxServer) -> None:
    with InfluxDBClient(url=influx.url, token=influx.token, org=influx.org) as client:
        client.write_api(write_options=SYNCHRONOUS).write(
            bucket=influx.bucket, record="channel,bench=b1,channel=ch0 voltage_v=1.25 1000000000"
        )
    assert _flux_values(influx, "channel") == [1.25]
    assert influx.count("channel", "voltage_v") == 1


def test_data_outlives_a_stop_and_a_start_on_the_same_port(influx: InfluxServer) -> None:
    with InfluxDBClient(url=influx.url, token=influx.token, org=influx.org) as client:
        client.write_api(write_options=SYNCHRONOUS).write(
            bucket=influx.bucket, record="scan duration_s=0.001 2000000000"
        )
    port = influx.port
    influx.stop()
    assert not influx.running
    influx.start()
    assert influx.port == port
    assert influx.count("scan", "duration_s") == 1
