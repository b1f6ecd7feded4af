-- wrk: POST JPEG bodies (raw image/jpeg), cycling over the files listed in $SCONE_WRK_FILES (":"-separated),
-- to the path of the URL given to wrk (e.g. /v1/describe or /v1/maps/big/localize?fx=..). One line of JSON
-- with the figures is printed at the end, after "SCONE-WRK-JSON ", for load-tests/lib/harness.py.
-- $SCONE_WRK_MAX_REQUESTS, when set, stops each wrk thread after that many responses.
-- $SCONE_WRK_TARGETS instead (";"-separated "path|file" pairs) gives each body its own path, and a path under
-- /v1/maps/{map_id}/ also the `x-scone-map-id` header, as a client of the router sends it (load-tests/replicas).
--
--   SCONE_WRK_FILES=a.jpg:b.jpg wrk -t1 -c4 -d30s --timeout 60s -s post-jpeg.lua http://127.0.0.1:18151/v1/describe

local function read(file)
  local h = assert(io.open(file, "rb"))
  local body = h:read("*a")
  h:close()
  return body
end

local targets = {}
for f in string.gmatch(os.getenv("SCONE_WRK_FILES") or "", "[^:]+") do
  targets[#targets + 1] = { body = read(f) }
end
for pair in string.gmatch(os.getenv("SCONE_WRK_TARGETS") or "", "[^;]+") do
  local path, file = string.match(pair, "^(.-)|(.+)$")
  targets[#targets + 1] = { path = path, map = string.match(path, "^/v1/maps/([^/?]+)/"), body = read(file) }
end
assert(#targets > 0, "neither SCONE_WRK_FILES nor SCONE_WRK_TARGETS lists a file")

local i = 0
request = function()
  i = i % #targets + 1
  local t = targets[i]
  local headers = { ["Content-Type"] = "image/jpeg" }
  if t.map then
    headers["x-scone-map-id"] = t.map
  end
  return wrk.format("POST", t.path, headers, t.body)
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
