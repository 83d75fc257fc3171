-- Framing and decoding for the Progwhiz dissector (whiztap wireshark-dissector):
-- one direction's bytes into items as whiztap's framer cuts them, and what each
-- item's bytes say on their own, as its codec decodes them.  Everything it knows
-- of the protocol is in T, generated from analyzer/protocol.

local FR, HEAD = T.framing, T.headers
local NEED, WAIT = "need", "wait"
local M = {}  -- message names (the generator checks each one this file uses)
for name in pairs(T.messages) do M[name] = name end
local WORD_MESSAGE = {}
for name, m in pairs(T.messages) do
    if T.handshake.server_steps[m.title] then WORD_MESSAGE[m.title] = name end
end
local HEADERS = {HEAD.command, HEAD.response, HEAD.config}
local SYNC = {HEAD.command, HEAD.response, HEAD.config, FR.words[1], FR.words[2], FR.words[3], FR.jpeg, FR.png, "\r", "\n"}
local SYNC_LONGEST = 0
for _, t in ipairs(SYNC) do SYNC_LONGEST = math.max(SYNC_LONGEST, #t) end
local RULE = {}
for _, r in ipairs(T.rules) do RULE[r.id] = r end

-- -- framing: one direction's bytes into items (positions are 0-based, as in whiztap's framer) --

local function starts(s, prefix) return s:sub(1, #prefix) == prefix end
local function sub(f, a, b) return f.buf:sub(a + 1, b) end
local function byte(f, i) return f.buf:byte(i + 1) end
local function digits(s) return #s > 0 and not s:find("[^0-9]") end

-- The first ``s`` lying wholly in [from, stop), or nil.
local function find(f, s, from, stop)
    local i = f.buf:find(s, from + 1, true)
    if i and i - 1 + #s <= stop then return i - 1 end
end

local function find_any(f, tokens, from, stop)
    local best
    for _, t in ipairs(tokens) do
        local i = find(f, t, from, stop)
        if i and (not best or i < best) then best = i end
    end
    return best
end

local function is_image(f, pos) return starts(f.buf:sub(pos + 1), FR.jpeg) or starts(f.buf:sub(pos + 1), FR.png) end

local function garbage(f, pos, reason)
    local m = find_any(f, SYNC, pos + 1, f.window)
    if m then return m - pos, "unframed", reason end
    if f.window - pos >= FR.max_item then return FR.max_item - SYNC_LONGEST + 1, "unframed", "oversize" end
    if f.final then return f.window - pos, "unframed", reason end
    return WAIT
end

local function scan_text(f, pos)
    local head = sub(f, pos, pos + 4)
    if head ~= HEAD.command and head ~= HEAD.response then
        if #head < 4 and (starts(HEAD.command, head) or starts(HEAD.response, head)) then return NEED end
        return nil
    end
    local kind = head == HEAD.command and "command" or "response"
    local body_end = pos + 4 + FR.text_frame_max
    local stop = math.min(f.window, body_end + 3)
    local t, h = find(f, FR.trailer, pos + 4, stop), find_any(f, HEADERS, pos + 4, stop)
    if t and (not h or h > t) then return t + 4 - pos, kind end
    if h then return h - pos, "unframed", "truncated" end
    if f.window < body_end + 3 then return NEED end
    return garbage(f, pos, "truncated")
end

-- Set Configuration: the trailer only where whole triples and the checksum end.
local function scan_set_config(f, pos, body, pad, trailer)
    local header = find_any(f, HEADERS, body, f.window)
    local stop = header or f.window
    local q = body + pad
    while q + #trailer <= f.window and q < stop do
        if sub(f, q, q + #trailer) == trailer then return q + #trailer - pos, "set_config" end
        q = q + 3
    end
    if header then return header - pos, "unframed", "truncated" end
    return NEED
end

local function scan_sr1(f, pos)
    local head = sub(f, pos, math.min(f.window, pos + 8))
    if not starts(head, HEAD.config) then
        return (#head < 4 and starts(HEAD.config, head)) and NEED or nil
    end
    if #head < 8 and starts(FR.set_config_prefix, head) then return NEED end
    if head == FR.set_config_prefix then return scan_set_config(f, pos, pos + 8, 1, FR.set_config_trailer) end
    local count = byte(f, pos + 4)
    local total = 4 + 1 + 3 * count + 4
    local body = sub(f, pos + 5, math.min(f.window, pos + total - 4))
    if count ~= FR.layout_data1 or digits(body) or #body == 0 then
        if f.window - pos < total then return NEED end
        if sub(f, pos + total - 4, pos + total) == FR.trailer then return total, "config" end
    end
    if count == FR.layout_data1 then return scan_set_config(f, pos, pos + 5, 2, FR.trailer) end
    return garbage(f, pos, "truncated")
end

local function scan_handshake(f, pos)
    for _, word in ipairs(FR.words) do
        if pos + #word <= f.window and sub(f, pos, pos + #word) == word then return #word, "handshake" end
    end
    local tail = sub(f, pos, f.window)
    for _, word in ipairs(FR.words) do
        if #tail < #word and starts(word, tail) then return NEED end
    end
end

local function scan_eol(f, pos)
    local first = byte(f, pos)
    if first == 0x0A then return 1, "eol" end
    if first ~= 0x0D then return nil end
    if pos + 1 == f.window then
        if f.final then return 1, "eol" end
        return NEED
    end
    return byte(f, pos + 1) == 0x0A and 2 or 1, "eol"
end

local function image_start(f, pos, signature)
    local n = math.min(f.n, pos + FR.max_image)
    local head = sub(f, pos, math.min(n, pos + #signature))
    if #head == 0 or not starts(signature, head) then return nil end
    if #head < #signature then return NEED end
    return n
end

-- Entropy-coded JPEG data: FF 00 is a stuffed byte, FF D0-D7 restarts, FF D9 the end.
local function walk_entropy(f, pos, n, i)
    while true do
        local j = find(f, "\255", i, n)
        if not j or j + 1 >= n then return NEED end
        local nxt = byte(f, j + 1)
        if nxt == 0xD9 then return j + 2 - pos, "image" end
        if nxt == 0xFF then
            i = j + 1
        elseif nxt == 0x00 or (nxt >= 0xD0 and nxt <= 0xD7) then
            i = j + 2
        else
            if j + 4 > n then return NEED end
            i = j + 2 + byte(f, j + 2) * 256 + byte(f, j + 3)
        end
    end
end

local function scan_jpeg(f, pos)
    local n = image_start(f, pos, FR.jpeg)
    if n == nil or n == NEED then return n end
    local i = pos + 2
    while true do
        if i + 2 > n then return NEED end
        if byte(f, i) ~= 0xFF then return garbage(f, pos, "garbage") end
        local marker = byte(f, i + 1)
        if marker == 0xFF then
            i = i + 1
        elseif marker == 0xD9 then
            return i + 2 - pos, "image"
        elseif (marker >= 0xD0 and marker <= 0xD7) or marker == 0x01 then
            i = i + 2
        else
            if i + 4 > n then return NEED end
            local length = byte(f, i + 2) * 256 + byte(f, i + 3)
            if length < 2 then return garbage(f, pos, "garbage") end
            i = i + 2 + length
            if marker == 0xDA then return walk_entropy(f, pos, n, i) end
        end
    end
end

local function scan_png(f, pos)
    local n = image_start(f, pos, FR.png)
    if n == nil or n == NEED then return n end
    local i = pos + 8
    while true do
        if i + 8 > n then return NEED end
        local length = ((byte(f, i) * 256 + byte(f, i + 1)) * 256 + byte(f, i + 2)) * 256 + byte(f, i + 3)
        local chunk = sub(f, i + 4, i + 8)
        if not chunk:find("^%a%a%a%a$") then return garbage(f, pos, "garbage") end
        if chunk == "IEND" then
            if i + 12 + length > n then return NEED end
            return i + 12 + length - pos, "image"
        end
        i = i + 12 + length
    end
end

local SCANNERS = {scan_text, scan_sr1, scan_handshake, scan_eol, scan_jpeg, scan_png}
local scan_item

-- After 'sendchkpass' the client's bytes up to a line break or a frame header
-- are its password.  Unlike whiztap's framer, which also ends it at the
-- server's verdict, a password here ends with its TCP segment at the latest.
local function scan_password(f, pos)
    local cut = f.window
    for _, token in ipairs({"\r", "\n", HEADERS[1], HEADERS[2], HEADERS[3]}) do
        local i = find(f, token, pos, f.window)
        if i and i < cut then cut = i end
    end
    f.password = false
    if cut == pos then return scan_item(f, pos) end
    return cut - pos, "password"
end

local function wait_or_cut(f, pos)
    local pending = f.n - pos
    local limit = is_image(f, pos) and FR.max_image or FR.max_item
    if pending >= limit then return limit, "unframed", "oversize" end
    if f.final then return pending, "unframed", "truncated" end
end

-- The item at ``pos``: its length, kind and (unframed) reason; nil to wait for more bytes.
scan_item = function(f, pos)
    f.window = math.min(f.n, pos + FR.max_item)
    local n, kind, reason
    if f.password then
        n, kind, reason = scan_password(f, pos)
    else
        for _, scanner in ipairs(SCANNERS) do
            n, kind, reason = scanner(f, pos)
            if n ~= nil then break end
        end
        if n == nil then n, kind, reason = garbage(f, pos, "garbage") end
    end
    if n == NEED then return wait_or_cut(f, pos) end
    if n == WAIT or n == nil then return nil end
    if n > FR.max_item then
        local limit = is_image(f, pos) and FR.max_image or FR.max_item
        if n > limit then n, kind, reason = limit, "unframed", "oversize" end
    end
    return n, kind, reason
end

-- Who sends these opening bytes of a conversation: "client", "server" or nil (cannot tell).
local function opener(head)
    if starts(head, HEAD.command) or starts(head, FR.set_config_prefix) then return "client" end
    if starts(head, HEAD.response) or starts(head, HEAD.config) then return "server" end
    for _, word in ipairs(FR.words) do
        if starts(head, word) then return "server" end
    end
end

-- -- decoding: what one item's bytes say on their own ----------------------------------

-- a count and its noun agreeing, digits grouped by threes: whiztap's plural()
local function plural(n, word, words)
    local digits = tostring(n):reverse():gsub("(%d%d%d)", "%1,"):reverse():gsub("^,", "")
    return digits .. " " .. (n == 1 and word or (words or word .. "s"))
end

local function show_bytes(s)
    return (s:gsub("[^ -~]", function(c) return ("\\x%02x"):format(c:byte()) end))
end

local function add(list, rule, detail) list[#list + 1] = {rule = rule, detail = detail} end
local function msg(name, fields) fields = fields or {} fields.name = name return fields end
local function title(m) return T.messages[m.name].title end

local function split(s, sep)
    local out, i = {}, 1
    while true do
        local j = s:find(sep, i, true)
        if not j then out[#out + 1] = s:sub(i) return out end
        out[#out + 1] = s:sub(i, j - 1)
        i = j + #sep
    end
end

local function parse_fields(raw, out)
    local body = raw:sub(5, -5)
    local fields = split(body, "--")
    if body:find(" ", 1, true) then
        add(out, "PW-SYNTAX-SPACE", ("space at offset %d of the frame"):format(raw:find(" ", 1, true) - 1))
        fields = split((body:gsub(" ", "")), "--")
    end
    if #fields ~= 3 or not (digits(fields[1]) and digits(fields[2]) and digits(fields[3])) then
        add(out, "PW-SYNTAX-FIELDS", "expected three decimal fields separated by '--', got " .. show_bytes(body))
        return nil
    end
    for k = 1, 3 do
        if #fields[k] > 1 and fields[k]:sub(1, 1) == "0" then
            add(out, "PW-SYNTAX-LEADING-ZERO", ("Data%d written as %s"):format(k, fields[k]))
        end
        if #fields[k] > T.field_widths[k] then
            add(out, "PW-SYNTAX-WIDTH", ("Data%d may be at most %d digits, got %d"):format(k, T.field_widths[k], #fields[k]))
        end
    end
    return tonumber(fields[1]), tonumber(fields[2]), tonumber(fields[3])
end

local function one(m, out, fields) return {message = m, candidates = {m}, violations = out, fields = fields} end

local function fixed(out, name, value, expected, what)
    if value ~= expected then
        add(out, "PW-FIXED-FIELD", ("%s: %s must be %d, got %d"):format(what, name, expected, value))
    end
end

local function check_channel(out, value)
    if value > T.max.channel then add(out, "PW-RANGE-CHANNEL", ("channel must be 0-%d, got %d"):format(T.max.channel, value)) end
end

local function script_message(d3)
    local C = T.codes
    if d3 >= C.internal[1] and d3 <= C.internal[2] then return msg(M.PlayInternalScript, {script = d3}) end
    if d3 >= C.external[1] and d3 <= C.external[2] then return msg(M.PlayExternalScript, {script = d3}) end
    if d3 == C.stop_internal then return msg(M.StopInternalScript) end
    if d3 == C.stop_external then return msg(M.StopExternalScript) end
end

local function decode_command(raw)
    local out, C = {}, T.codes
    local d1, d2, d3 = parse_fields(raw, out)
    if d1 == nil then return {candidates = {}, violations = out} end
    local fields = {d1, d2, d3}
    if d3 == C.servo_position then
        fixed(out, "Data2", d2, 0, T.messages[M.ServoPositionRequest].title)
        check_channel(out, d1)
        return one(msg(M.ServoPositionRequest, {channel = d1}), out, fields)
    end
    local script = script_message(d3)
    if script then
        fixed(out, "Data1", d1, 0, title(script))
        fixed(out, "Data2", d2, 0, title(script))
        return one(script, out, fields)
    end
    if d3 ~= 0 then
        if d3 > C.stop_internal then
            add(out, "PW-RANGE-SCRIPT", ("script code must be 11-266, 267, 269 or 270-275, got %d"):format(d3))
        else
            add(out, "PW-UNKNOWN-COMMAND", ("Data3 must be 0, 2, a script number or a stop code, got %d"):format(d3))
        end
        return one(msg(M.UnknownCommand, {data1 = d1, data2 = d2, data3 = d3}), out, fields)
    end
    for code, name in pairs({[C.fetch_config] = M.FetchConfiguration, [C.fetch_camera] = M.FetchCameraImage}) do
        if d1 == code then
            fixed(out, "Data2", d2, 0, T.messages[name].title)
            return one(msg(name), out, fields)
        end
    end
    check_channel(out, d1)
    if d2 == 0 then
        return {candidates = {msg(M.SensorRequest, {channel = d1}), msg(M.DeactivateSwitch, {channel = d1}),
                              msg(M.NormalSend, {channel = d1, value = 0})}, violations = out, fields = fields}
    end
    if d2 == 1 then
        return {candidates = {msg(M.ActivateSwitch, {channel = d1}), msg(M.NormalSend, {channel = d1, value = 1})},
                violations = out, fields = fields}
    end
    if d2 > T.max.send_value then
        add(out, "PW-RANGE-SEND-VALUE", ("Normal Send value must be 0-%d, got %d"):format(T.max.send_value, d2))
    end
    return one(msg(M.NormalSend, {channel = d1, value = d2}), out, fields)
end

local function decode_response(raw)
    local out = {}
    local d1, d2, d3 = parse_fields(raw, out)
    if d1 == nil then return {candidates = {}, violations = out} end
    check_channel(out, d1)
    fixed(out, "Data3", d3, 0, T.messages[M.ChannelResponse].title)
    return one(msg(M.ChannelResponse, {channel = d1, data = d2}), out, {d1, d2, d3})
end

local function decode_config(raw)
    local out = {}
    local count, body = raw:byte(5), raw:sub(6, -5)
    if count > T.max.config_channels then
        add(out, "PW-CFG-COUNT", ("channel count must be at most %d, got %d"):format(T.max.config_channels, count))
    end
    local bad = body:find("[^0-9]")
    if bad then
        add(out, "PW-CFG-DIGIT", ("channel %d: expected a digit, got byte 0x%02x"):format(math.floor((bad - 1) / 3), body:byte(bad)))
        return {candidates = {}, violations = out}
    end
    local channels = {}
    for ch = 0, count - 1 do
        local unit, unused, switch = body:byte(3 * ch + 1) - 48, body:byte(3 * ch + 2) - 48, body:byte(3 * ch + 3) - 48
        if unit > 2 then add(out, "PW-CFG-UNIT", ("channel %d: unit type must be 0, 1 or 2, got %d"):format(ch, unit)) end
        if unused ~= 0 then add(out, "PW-CFG-UNUSED", ("channel %d: unused field must be 0, got %d"):format(ch, unused)) end
        if switch > 1 then add(out, "PW-CFG-SWITCH-TYPE", ("channel %d: switch type must be 0 or 1, got %d"):format(ch, switch)) end
        channels[#channels + 1] = {unit_type = unit, unused = unused, switch_type = switch}
    end
    return one(msg(M.ConfigurationSettings, {channels = channels}), out)
end

local function decode_set_config(raw)
    local out, payload = {}, nil
    if starts(raw, FR.set_config_prefix) then
        payload = raw:sub(#FR.set_config_prefix + 1, #raw - #FR.set_config_trailer)
    else
        add(out, "PW-SETCFG-FORM", "Data1 sent as the raw byte 25 (the Layout line's reading); "
            .. "expected the text '25--' as in the spec's example")
        payload = raw:sub(6, #raw - #FR.trailer - 1)
        if raw:sub(-5, -5) ~= "0" then add(out, "PW-SETCFG-TRAILER", "expected '0' before -ss1, got " .. show_bytes(raw:sub(-5, -5))) end
    end
    local entries = {}
    for i = 1, #payload - 1, 3 do
        local dev, port, unit = payload:byte(i, i + 2)
        local n = #entries
        if dev > T.max.device then add(out, "PW-SETCFG-DEV", ("entry %d: Dev# must be 0-%d, got %d"):format(n, T.max.device, dev)) end
        if port > T.max.channel then add(out, "PW-SETCFG-PORT", ("entry %d: Port# must be 0-%d, got %d"):format(n, T.max.channel, port)) end
        if unit > 2 then add(out, "PW-SETCFG-UNIT", ("entry %d: unit type must be 0, 1 or 2, got %d"):format(n, unit)) end
        entries[#entries + 1] = {device = dev, port = port, unit_type = unit}
    end
    if #entries == 0 then add(out, "PW-SETCFG-EMPTY", "no (Dev#, Port#, unit type) entries") end
    return one(msg(M.SetConfiguration, {entries = entries, checksum = payload:byte(-1)}), out)
end

local function decode(item)
    local kind, raw = item.kind, item.raw
    if kind == "command" then return decode_command(raw) end
    if kind == "response" then return decode_response(raw) end
    if kind == "config" then return decode_config(raw) end
    if kind == "set_config" then return decode_set_config(raw) end
    if kind == "handshake" then return one(msg(WORD_MESSAGE[raw]), {}) end
    if kind == "password" then return one(msg(M.Password, {length = #raw}), {}) end
    if kind == "image" then
        return one(msg(M.CameraImage, {format = starts(raw, FR.jpeg) and "jpeg" or "png", size = #raw}), {})
    end
    if kind == "eol" then return {candidates = {}, violations = {}} end
    return {candidates = {}, violations = {{rule = T.unframed_rules[item.reason or "garbage"],
                                            detail = ("%s forming no message"):format(plural(#raw, "byte"))}}}
end

return {FR = FR, M = M, RULE = RULE, scan_item = scan_item, opener = opener, decode = decode, add = add,
        title = title, show_bytes = show_bytes, plural = plural}
