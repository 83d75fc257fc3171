-- -- what Wireshark shows: an item's tree, the dissector, the end of a stream ---------------

local function describe(item, decoded, rec)
    local m = rec and rec.message or decoded.message
    if m then
        if m.name == M.ChannelResponse and rec and rec.request then
            if rec.data_as == "servo" then return ("Servo %d position %g"):format(m.channel, m.data / 4) end
            return ("Sensor value ch %d = %d"):format(m.channel, m.data)
        end
        local template = T.messages[m.name].describe
        if template then return (template:gsub("{(%w+)}", function(k) return tostring(m[k]) end)) end
        if m.name == M.ConfigurationSettings then
            local counts, parts = {}, {}
            for _, c in ipairs(m.channels) do counts[c.unit_type] = (counts[c.unit_type] or 0) + 1 end
            for unit = 0, 2 do
                if counts[unit] then parts[#parts + 1] = ("%d %s"):format(counts[unit], T.units[unit]) end
            end
            local listed = #parts > 0 and (" (" .. table.concat(parts, ", ") .. ")") or ""
            return ("%s: %s%s"):format(title(m), plural(#m.channels, "channel"), listed)
        end
        if m.name == M.SetConfiguration then
            return ("Set Configuration: %s, checksum %d"):format(plural(#m.entries, "entry", "entries"), m.checksum)
        end
        if m.name == M.Password then return ("Password (%s)"):format(plural(m.length, "byte")) end
        return ("Camera image (%s, %s)"):format(m.format, plural(m.size, "byte"))
    end
    if #decoded.candidates > 0 then
        local each = {}
        for _, c in ipairs(decoded.candidates) do each[#each + 1] = describe(item, {candidates = {}, message = c}) end
        return table.concat(each, " / ") .. " (ambiguous)"
    end
    if item.kind == "unframed" then return ("unframed bytes (%s)"):format(item.reason) end
    if item.kind == "eol" then return "line break" end
    return "malformed " .. item.kind
end

local function add_message_fields(sub, range, m)
    for _, key in ipairs({"channel", "value", "script", "data", "checksum"}) do
        if m[key] ~= nil and F[key] then sub:add(F[key], range, m[key]) end
    end
    if m.name == M.ConfigurationSettings then
        sub:add(F.config_count, range, #m.channels)
        for i, c in ipairs(m.channels) do
            local ch = sub:add(range, ("Channel %d: %s"):format(i - 1, T.units[c.unit_type] or ("unit " .. c.unit_type)))
            for _, key in ipairs({"unit_type", "unused", "switch_type"}) do ch:add(F["channel_config." .. key], range, c[key]) end
        end
    elseif m.name == M.SetConfiguration then
        for i, e in ipairs(m.entries) do
            local entry = sub:add(range, ("Entry %d: Dev# %d, Port# %d, %s"):format(i - 1, e.device, e.port, T.units[e.unit_type] or "?"))
            for _, key in ipairs({"device", "port", "unit_type"}) do entry:add(F["set_config_entry." .. key], range, e[key]) end
        end
    elseif m.name == M.Password then
        sub:add(F["password.secret"], range)
        sub:add(F.length, range, m.length)
    elseif m.name == M.CameraImage then
        sub:add(F["camera_image.format"], range, m.format)
        sub:add(F["camera_image.data"], range)
        sub:add(F.length, range, m.size)
    end
end

local function add_pairing(sub, range, pinfo, rec)
    if rec.request then
        sub:add(F.request_in, range, rec.request.frame)
        local secs = math.floor(rec.latency)
        sub:add(F.latency, range, NSTime.new(secs, math.floor((rec.latency - secs) * 1e9 + 0.5)))
    end
    if rec.data_as == "sensor" then sub:add(F.sensor_value, range, rec.message.data) end
    if rec.data_as == "servo" then sub:add(F.servo_position, range, rec.message.data / 4) end
    if rec.data_from then sub:add(F.data_from, range, rec.data_as .. " data, by " .. rec.data_from) end
    local p = rec.pending
    if p and p.answered_in then sub:add(F.response_in, range, p.answered_in) end
    if p and p.certain and pinfo.visited and (p.unanswered or not p.answered_in) then
        return {{rule = "PW-PAIR-UNANSWERED", detail = ("%s: %s"):format(p.title, p.unanswered or "the capture ended first")}}
    end
    return {}
end

local function show(tree, pinfo, item, dir, rec, shown)
    local decoded = P.decode(item)
    local text = describe(item, decoded, rec)
    shown[#shown + 1] = text
    local range = item.range
    local sub = tree:add(proto, range, "Progwhiz, " .. text)
    sub:add(F.kind, range, item.kind)
    sub:add(F.direction, range, dir)
    if item.reason then sub:add(F.reason, range, item.reason) end
    local m = rec and rec.message or decoded.message
    if m then
        sub:add(F.message, range, title(m))
    else
        for _, c in ipairs(decoded.candidates) do sub:add(F.candidate, range, title(c)) end
        if decoded.candidates[1] then sub:add(F.channel, range, decoded.candidates[1].channel) end
    end
    sub:add(F.meaning, range, text)
    if decoded.fields then
        for k = 1, 3 do sub:add(F["data" .. k], range, decoded.fields[k]) end
    end
    if m then add_message_fields(sub, range, m) end
    local late = rec and add_pairing(sub, range, pinfo, rec) or {}
    for _, list in ipairs({rec and rec.violations or decoded.violations, late}) do
        for _, v in ipairs(list) do
            sub:add(F.rule, range, v.rule)
            sub:add_tvb_expert_info(E[v.rule], range, v.rule .. ": " .. v.detail)
        end
    end
end

local function conversation(pinfo)
    local stream = f_stream()  -- missing only where Wireshark builds no tree (tshark -2 without -R)
    local ends = {tostring(pinfo.src) .. "|" .. pinfo.src_port, tostring(pinfo.dst) .. "|" .. pinfo.dst_port}
    table.sort(ends)
    local key = stream and stream.value or table.concat(ends, " ")
    local conv = convs[key]
    if conv == nil then
        conv = {state = "start", mode = "unknown", map = {}, commands = 0, last = {}, password = false,
                pending = {}, expired = {}, partial = {}}
        convs[key] = conv
    end
    return conv
end

-- Which way these bytes go: the server is on the port preference's side, else
-- the side whose opening bytes a server sends, else the lower port's.
local function direction(conv, pinfo, head)
    local src = tostring(pinfo.src) .. "|" .. pinfo.src_port
    if conv.server == nil then
        local dst, port = tostring(pinfo.dst) .. "|" .. pinfo.dst_port, proto.prefs.port
        local who = P.opener(head)
        if pinfo.dst_port == port and pinfo.src_port ~= port then who = "client"
        elseif pinfo.src_port == port and pinfo.dst_port ~= port then who = "server"
        elseif who == nil then who = pinfo.src_port < pinfo.dst_port and "server" or "client" end
        conv.server = who == "server" and src or dst
    end
    return src == conv.server and "s2c" or "c2s"
end

-- Frame ``buf`` and show each item; the offset where an incomplete item begins, if one does.
local function items(tvb, pinfo, tree, conv, dir, call, f)
    local shown, first, pos = {}, not pinfo.visited, 0
    while pos < f.n do
        local n, kind, reason = P.scan_item(f, pos)
        if n == nil then break end
        if dir == "c2s" and first then conv.password = f.password end
        local item = {kind = kind, reason = reason, raw = f.buf:sub(pos + 1, pos + n), range = tvb:range(pos, n)}
        local key = call .. ":" .. pos
        if first and results[key] == nil then
            results[key] = observe(conv, dir, item, P.decode(item), pinfo.abs_ts, pinfo.number)
        end
        show(tree, pinfo, item, dir, results[key], shown)
        pos = pos + n
    end
    if #shown > 0 then
        pinfo.cols.protocol:set("Progwhiz")
        pinfo.cols.info:set(table.concat(shown, "; "))
    end
    return pos < f.n and pos or nil
end

local function dissect(tvb, pinfo, tree)
    local len = tvb:len()
    if len == 0 then return 0 end
    local buf = tvb:raw()
    local conv = conversation(pinfo)
    local dir = direction(conv, pinfo, buf:sub(1, 17))
    local call = ("%d:%d:%d"):format(pinfo.number, tvb:offset(), len)
    if not pinfo.visited then starts[call] = dir == "c2s" and conv.password end
    local f = {buf = buf, n = len, final = false, password = starts[call] or false}
    local rest = items(tvb, pinfo, tree, conv, dir, call, f)
    if not pinfo.visited then conv.partial[dir] = rest and buf:sub(rest + 1) or nil end
    if rest then
        pinfo.desegment_offset = rest
        pinfo.desegment_len = DESEGMENT_ONE_MORE_SEGMENT
    end
    return len
end
proto.dissector = dissect

-- A stream that ends (FIN or RST) in the middle of an item: whiztap's framer
-- cuts what is left as it does at the end of a connection; TCP never hands
-- those bytes on, so this postdissector shows them on the packet that ended it.
local ending = Proto("progwhiz_end", "Progwhiz end of stream")
function ending.dissector(tvb, pinfo, tree)
    local fin, rst, stream = f_fin(), f_rst(), f_stream()
    if not (stream and ((fin and fin.value) or (rst and rst.value))) or convs[stream.value] == nil then return end
    local conv, call = convs[stream.value], ("end:%d"):format(pinfo.number)
    local dir = (tostring(pinfo.src) .. "|" .. pinfo.src_port) == conv.server and "s2c" or "c2s"
    if not pinfo.visited then
        starts[call] = conv.partial[dir]
        conv.partial[dir] = nil
    end
    local bytes = starts[call]
    if not bytes then return end
    local left = ByteArray.new(bytes, true):tvb("Progwhiz: bytes left when the stream ended")
    local f = {buf = bytes, n = #bytes, final = true, password = false}
    items(left, pinfo, tree, conv, dir, call, f)
end
register_postdissector(ending)

local function heuristic(tvb, pinfo, tree)
    if tvb:len() == 0 or P.opener(tvb:raw(0, math.min(tvb:len(), 17))) == nil then return false end
    pinfo.conversation = proto
    dissect(tvb, pinfo, tree)
    return true
end
proto:register_heuristic("tcp", heuristic)

local registered = T.defaults.port
DissectorTable.get("tcp.port"):add(registered, proto)
function proto.prefs_changed()
    if proto.prefs.port ~= registered then
        local tcp = DissectorTable.get("tcp.port")
        if registered ~= 0 then tcp:remove(registered, proto) end
        if proto.prefs.port ~= 0 then tcp:add(proto.prefs.port, proto) end
        registered = proto.prefs.port
    end
end
