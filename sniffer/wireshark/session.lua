-- The Progwhiz dissector's conversations and tree (whiztap wireshark-dissector).
-- P is the framing and decoding above.  Each TCP conversation is followed as
-- whiztap's session follows a connection: the Winsock handshake, the channel
-- map the server's Configuration Settings (or a good Set Configuration) made,
-- and which request each answer answers.  That needs the packets in order, so
-- it is worked out on Wireshark's first pass and kept per item; a request
-- never answered is known only once the whole file was read, so it shows on
-- the second pass (Wireshark's details pane, or tshark -2).

local M, RULE, add, title, plural = P.M, P.RULE, P.add, P.title, P.plural
local proto = Proto("progwhiz", "Progwhiz Robotics Server API")
local F = {
    kind = ProtoField.string("progwhiz.kind", "Item kind"),
    direction = ProtoField.string("progwhiz.direction", "Direction", base.ASCII, "c2s: client to server"),
    message = ProtoField.string("progwhiz.message", "Message"),
    candidate = ProtoField.string("progwhiz.candidate", "May be", base.ASCII, "a meaning of an ambiguous frame"),
    meaning = ProtoField.string("progwhiz.meaning", "Meaning"),
    reason = ProtoField.string("progwhiz.reason", "Unframed because"),
    rule = ProtoField.string("progwhiz.rule", "Rule broken", base.ASCII, "a whiztap rule id (whiztap rules)"),
    length = ProtoField.uint32("progwhiz.length", "Length"),
    config_count = ProtoField.uint32("progwhiz.config_count", "Channel count"),
    sensor_value = ProtoField.uint32("progwhiz.sensor_value", "Sensor value"),
    servo_position = ProtoField.double("progwhiz.servo_position", "Servo position", "servo data / 4"),
    data_from = ProtoField.string("progwhiz.data_from", "Data read as", base.ASCII,
                                  "what says whether a response holds sensor or servo data"),
    request_in = ProtoField.framenum("progwhiz.request_in", "Answers the request in frame"),
    response_in = ProtoField.framenum("progwhiz.response_in", "Answered in frame"),
    latency = ProtoField.relative_time("progwhiz.latency", "Latency"),
}
for _, field in ipairs(T.fields) do
    local abbr = "progwhiz." .. field.key
    if field.type == "uint32" then
        F[field.key] = ProtoField.uint32(abbr, field.name, base.DEC, field.key:find("unit_type") and T.units or nil)
    elseif field.type == "bytes" then
        F[field.key] = ProtoField.bytes(abbr, field.name)
    else
        F[field.key] = ProtoField.string(abbr, field.name)
    end
end
local fields = {}
for _, field in pairs(F) do fields[#fields + 1] = field end
proto.fields = fields

local E = {}
local function group(id)
    if id:find("^PW%-SYNTAX") or id == "PW-FRAME-GARBAGE" or id == "PW-FRAME-TRUNCATED" or id == "PW-FRAME-OVERSIZE" then
        return expert.group.MALFORMED
    end
    if id:find("^PW%-HS") or id:find("CONFIG%-FIRST$") or id:find("^PW%-PAIR") then return expert.group.SEQUENCE end
    return expert.group.PROTOCOL
end
local SEVERITY = {error = expert.severity.ERROR, warn = expert.severity.WARN, note = expert.severity.NOTE}
local experts = {}
for _, r in ipairs(T.rules) do
    E[r.id] = ProtoExpert.new("progwhiz.expert." .. r.id:lower():gsub("-", "_"), r.id .. ": " .. r.summary,
                              group(r.id), SEVERITY[r.severity])
    experts[#experts + 1] = E[r.id]
end
proto.experts = experts

local rule_choices, default_rule = {}, 1
for i, r in ipairs(T.checksum_rules) do
    rule_choices[i] = {i, r.name, i}
    if r.name == T.defaults.checksum_rule then default_rule = i end
end
proto.prefs.port = Pref.uint("TCP port", T.defaults.port, "The server's port; the heuristic finds Progwhiz on any other")
proto.prefs.checksum_rule = Pref.enum("Set Configuration checksum rule", default_rule,
                                      "The rule PW-SETCFG-CHECKSUM checks (whiztap rules)", rule_choices, false)
proto.prefs.answer_timeout = Pref.uint("Answer timeout (ms)", T.defaults.answer_timeout_ms,
                                       "How long a request may wait for its answer")

local f_stream, f_fin, f_rst = Field.new("tcp.stream"), Field.new("tcp.flags.fin"), Field.new("tcp.flags.reset")
local convs, results, starts = {}, {}, {}
function proto.init() convs, results, starts = {}, {}, {} end

-- -- the session of one conversation ------------------------------------------------------

local function advance(conv, step, out)
    local HS = T.handshake
    local row = HS.table[conv.state]
    local next_state, rule = row and row[step] and row[step][1], row and row[step] and row[step][2]
    if next_state == nil then
        next_state, rule = conv.state, conv.state == "failed" and "PW-HS-AFTER-FAILED" or "PW-HS-ORDER"
    end
    conv.mode = HS.mode_told[conv.state .. " " .. step] or conv.mode
    if rule then add(out, rule, ("got %s, expected %s"):format(HS.step_words[step], HS.expected[conv.state])) end
    conv.state = next_state
end

local function unit_of(conv, channel)
    local config = conv.map[channel]
    if config == nil or T.units[config.unit_type] == nil then return nil end
    return config.unit_type
end

local function names(candidates, sep)
    local out = {}
    for _, c in ipairs(candidates) do out[#out + 1] = title(c) end
    return table.concat(out, sep)
end

-- A command's meaning in the channel map, and the rule it breaks there.
local function command_meaning(conv, message, candidates, out)
    local channel = candidates[1] and candidates[1].channel
    if channel == nil then return message end
    local unit, mapped = unit_of(conv, channel), next(conv.map) ~= nil
    if message == nil then
        local fitting = {}
        for _, c in ipairs(candidates) do
            if unit ~= nil and T.unit_of_command[c.name] == unit then fitting[#fitting + 1] = c end
        end
        if #fitting == 1 then return fitting[1] end
        if unit ~= nil then
            add(out, "PW-UNIT-MISMATCH", ("channel %d is a %s; the frame means %s"):format(channel, T.units[unit], names(candidates, " or ")))
        elseif mapped then
            add(out, "PW-CHANNEL-UNCONFIGURED", ("channel %d is not in the server's configuration"):format(channel))
        else
            add(out, "PW-AMBIGUOUS", "may be " .. names(candidates, ", "))
        end
        return nil
    end
    local needed = T.unit_of_command[message.name]
    if needed ~= nil and unit ~= nil and unit ~= needed then
        add(out, "PW-UNIT-MISMATCH", ("%s needs a %s; channel %d is a %s"):format(title(message), T.units[needed], channel, T.units[unit]))
    elseif needed ~= nil and unit == nil and mapped then
        add(out, "PW-CHANNEL-UNCONFIGURED", ("channel %d is not in the server's configuration"):format(channel))
    end
    return message
end

local function apply_set_config(conv, message, out)
    local rule = T.checksum_rules[proto.prefs.checksum_rule].name
    local expected = CHECKSUMS[rule](message.entries)
    if expected ~= message.checksum then
        add(out, "PW-SETCFG-CHECKSUM", ("expected %d (%s), got %d"):format(expected, rule, message.checksum))
        return
    end
    for _, v in ipairs(out) do
        if RULE[v.rule].severity == "error" then return end  -- a server would not apply it
    end
    for _, e in ipairs(message.entries) do conv.map[e.port] = {unit_type = e.unit_type, unused = 0, switch_type = 0} end
end

local function client_frame(conv, message, candidates, out)
    conv.commands = conv.commands + 1
    message = command_meaning(conv, message, candidates, out)
    if message and message.name == M.SetConfiguration then apply_set_config(conv, message, out) end
    if conv.commands == 1 and conv.state == "ready" and not (message and message.name == M.FetchConfiguration) then
        local what = message and title(message) or (#candidates > 0 and "an ambiguous frame" or "an undecodable frame")
        add(out, conv.mode == "vpn" and "PW-VPN-CONFIG-FIRST" or "PW-WINSOCK-CONFIG-FIRST", "first command was " .. what)
    end
    return message
end

local function frame(conv, dir, kind, message, candidates, out)
    if T.travels[kind] and T.travels[kind] ~= dir then
        add(out, "PW-DIRECTION", ("%s came from the %s"):format(T.kind_words[kind], dir == "c2s" and "client" or "server"))
        return message
    end
    advance(conv, dir == "s2c" and "server_frame" or (kind == "password" and "password" or "client_frame"), out)
    if dir == "c2s" and kind ~= "password" then message = client_frame(conv, message, candidates, out) end
    return message
end

local function server_handshake(conv, message, out)
    local step = T.handshake.server_steps[title(message)]
    if step ~= "sendchkpass" then conv.password = false end  -- the verdict ends the password
    local early = conv.state == "early_password"
    advance(conv, step, out)
    if step == "sendchkpass" and conv.state == "await_password" and not early then conv.password = true end
end

-- The oldest waiting request an answer fits (certain ones first, if asked).
local function take(list, kind, channel, certain_first)
    local sure, maybe
    for i, p in ipairs(list) do
        if p.kind == kind and p.channel == channel then
            if p.certain then sure = sure or i else maybe = maybe or i end
        end
    end
    local pick = sure
    if sure == nil or not certain_first then
        if sure == nil or (maybe and maybe < sure) then pick = maybe end
    end
    if pick then return table.remove(list, pick) end
end

local function expire(conv, t)
    local timeout = proto.prefs.answer_timeout / 1000
    while conv.pending[1] and t - conv.pending[1].t > timeout do
        local p = table.remove(conv.pending, 1)
        p.unanswered = ("no answer within %g s"):format(timeout)
        conv.expired[#conv.expired + 1] = p
        if #conv.expired > 1024 then table.remove(conv.expired, 1) end
    end
end

-- Sensor or servo data: the request says which, else the channel's configured unit.
local function response_data(conv, message, request, rec, out)
    local servo
    if request then
        servo = request.servo
        rec.data_as, rec.data_from = servo and "servo" or "sensor", ("the request in frame %d"):format(request.frame)
    else
        local unit = unit_of(conv, message.channel)
        if unit ~= nil then servo = unit == 0 end
        if unit == 0 or unit == 2 then
            rec.data_as, rec.data_from = servo and "servo" or "sensor", ("channel %d's configured unit"):format(message.channel)
        end
    end
    local limit, rule, what = T.max.servo, "PW-RANGE-SERVO", servo and "servo data" or "sensor or servo data"
    if servo == false then limit, rule, what = T.max.sensor, "PW-RANGE-SENSOR", "sensor data" end
    if message.data > limit then add(out, rule, ("%s must be 0-%d, got %d"):format(what, limit, message.data)) end
end

local function answer(conv, kind, message, t, rec, out)
    local channel = message and message.name == M.ChannelResponse and message.channel or nil
    local found = take(conv.pending, kind, channel, true) or take(conv.expired, kind, channel, false)
    if found then
        rec.request, rec.latency = found, t - found.t
        found.answered_in = rec.frame
    else
        add(out, "PW-PAIR-UNSOLICITED", ("no outstanding request is answered by %s"):format(T.kind_words[kind]))
    end
    if message and message.name == M.ConfigurationSettings then
        conv.map = {}
        for i, c in ipairs(message.channels) do conv.map[i - 1] = c end
    elseif message and message.name == M.ChannelResponse then
        response_data(conv, message, found, rec, out)
    end
end

local function await_answer(conv, message, candidates, t, rec)
    local kind, channel, certain
    if message then
        kind, channel, certain = T.answer_kind[message.name], message.channel, true
    else
        for _, c in ipairs(candidates) do
            if c.name == M.SensorRequest then kind, channel, certain = "response", c.channel, false end
        end
    end
    if kind then
        rec.pending = {kind = kind, channel = channel, certain = certain, t = t, frame = rec.frame,
                       servo = message ~= nil and message.name == M.ServoPositionRequest, title = message and title(message) or "request"}
        conv.pending[#conv.pending + 1] = rec.pending
    end
end

local SERVER_KINDS = {response = true, config = true, image = true}
local FRAME_KINDS = {command = true, set_config = true, response = true, config = true, image = true,
                     password = true, handshake = true}

-- One item in its conversation (first pass only): what it means there, and the rules it breaks.
local function observe(conv, dir, item, decoded, t, number)
    local out = {}
    for _, v in ipairs(decoded.violations) do out[#out + 1] = v end
    local rec = {message = decoded.message, violations = out, frame = number}
    local kind = item.kind
    if conv.pending[1] then expire(conv, t) end
    if kind == "handshake" and decoded.message and dir == "s2c" then
        server_handshake(conv, decoded.message, out)
    elseif FRAME_KINDS[kind] then
        rec.message = frame(conv, dir, kind, decoded.message, decoded.candidates, out)
    elseif kind == "eol" and conv.last[dir] ~= "handshake" and conv.last[dir] ~= "password" then
        local after = conv.last[dir] and ("after " .. T.kind_words[conv.last[dir]]) or "before anything else"
        add(out, "PW-FRAME-EOL", ("line break %s %s"):format(P.show_bytes(item.raw), after))
    end
    if dir == "s2c" and SERVER_KINDS[kind] then answer(conv, kind, rec.message, t, rec, out) end
    conv.last[dir] = kind
    if dir == "c2s" and kind == "command" then await_answer(conv, rec.message, decoded.candidates, t, rec) end
    return rec
end
