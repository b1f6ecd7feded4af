-- wrk: POST JPEG bodies (raw image/jpeg), cycling over the files listed in $SCONE_WRK_FILES (":"-separated),
-- to the path of the URL given to wrk (e.g. /v1/describe or /v1/maps/big/localize?fx=..). One line of JSON
-- with the figures is printed at the end, after "SCONE-WRK-JSON ", for load-tests/lib/harness.py.
-- $SCONE_WRK_MAX_REQUESTS, when set, stops each wrk thread after that many responses.
--
--   SCONE_WRK_FILES=a.jpg:b.jpg wrk -t1 -c4 -d30s --timeout 60s -s post-jpeg.lua http://127.0.0.1:18151/v1/describe

local bodies = {}
for f in string.gmatch(os.getenv("SCONE_WRK_FILES") or "", "[^:]+") do
  local h = assert(io.open(f, "rb"))
  bodies[#bodies + 1] = h:read("*a")
  h:close()
end
assert(#bodies > 0, "SCONE_WRK_FILES lists no file")

local i = 0
request = function()
  i = i % #bodies + 1
  return wrk.format("POST", nil, { ["Content-Type"] = "image/jpeg" }, bodies[i])
end

local max_requests = tonumber(os.getenv("SCONE_WRK_MAX_REQUESTS") or "")
if max_requests then
  local answered = 0
  response = function()
    answered = answered + 1
    if answered >= max_requests then
      wrk.thread:stop()
    end
  end
end

done = function(summary, latency, requests)
  local non2xx = summary.errors.status
  local socket = summary.errors.connect + summary.errors.read + summary.errors.write + summary.errors.timeout
  io.write(string.format(
    'SCONE-WRK-JSON {"requests": %d, "duration_s": %.3f, "rps": %.3f, "non2xx": %d, "socket_errors": %d, ' ..
    '"timeouts": %d, "p50_ms": %.3f, "p95_ms": %.3f, "p99_ms": %.3f, "max_ms": %.3f, "mean_ms": %.3f}\n',
    summary.requests, summary.duration / 1e6, summary.requests / (summary.duration / 1e6), non2xx, socket,
    summary.errors.timeout, latency:percentile(50) / 1e3, latency:percentile(95) / 1e3,
    latency:percentile(99) / 1e3, latency.max / 1e3, latency.mean / 1e3))
end
