-- Neovim (0.7+, headless) as the client of `kiln lsp`, driven by compiler/tests/lsp.rs:
-- plants an error in a header on disk, opens the shader that includes it, and records
-- diagnostics, a hover and two definitions as JSON in $KILN_LSP_OUT.
local root = os.getenv('KILN_LSP_ROOT')
local out = os.getenv('KILN_LSP_OUT')
local kiln = os.getenv('KILN')
local results = {}

local function line_of(lines, needle)
  for i, l in ipairs(lines) do
    if l:find(needle, 1, true) then return i - 1 end
  end
  error('no line with ' .. needle)
end

local function request(buf, method, params)
  local answers = vim.lsp.buf_request_sync(buf, method, params, 20000) or {}
  for _, a in pairs(answers) do
    if a.result then return a.result end
  end
  return nil
end

local function run()
  local header = root .. '/shaders/Common.ush'
  local hlines = vim.fn.readfile(header)
  hlines[line_of(hlines, 'return s.albedo;') + 1] = '    return s.albedo + oops;'
  vim.fn.writefile(hlines, header)

  local id = vim.lsp.start_client({
    cmd = { kiln, 'lsp' },
    root_dir = root,
    init_options = { permutation = { FULLY_ROUGH = 1 } },
  })
  assert(id, 'the client did not start')
  local shader = root .. '/shaders/Lit.usf'
  vim.cmd('edit ' .. shader)
  local buf = vim.api.nvim_get_current_buf()
  vim.lsp.buf_attach_client(buf, id)

  -- The header is not open: its diagnostics arrive on its URI all the same.
  local hbuf = vim.uri_to_bufnr(vim.uri_from_fname(header))
  local err = vim.diagnostic.severity.ERROR
  vim.wait(20000, function() return #vim.diagnostic.get(hbuf, { severity = err }) > 0 end, 50)
  local hd = vim.diagnostic.get(hbuf, { severity = err })
  results.header_error_line = hd[1] and hd[1].lnum
  results.header_error = hd[1] and hd[1].message

  local hint = vim.diagnostic.severity.HINT
  vim.wait(20000, function() return #vim.diagnostic.get(buf, { severity = hint }) > 0 end, 50)
  results.inactive = #vim.diagnostic.get(buf, { severity = hint })

  local lines = vim.api.nvim_buf_get_lines(buf, 0, -1, false)
  local uri = vim.uri_from_bufnr(buf)
  local l = line_of(lines, 'f32(NUM_LIGHTS)')
  local c = lines[l + 1]:find('NUM_LIGHTS', 1, true)
  local hover = request(buf, 'textDocument/hover', { textDocument = { uri = uri }, position = { line = l, character = c } })
  results.hover = hover and hover.contents and hover.contents.value

  local def = request(buf, 'textDocument/definition', { textDocument = { uri = uri }, position = { line = 0, character = 12 } })
  if def and def[1] then def = def[1] end
  results.include_definition = def and vim.uri_to_fname(def.uri)

  l = line_of(lines, 'shade(s')
  c = lines[l + 1]:find('shade', 1, true)
  def = request(buf, 'textDocument/definition', { textDocument = { uri = uri }, position = { line = l, character = c } })
  if def and def[1] then def = def[1] end
  results.function_definition = def and vim.uri_to_fname(def.uri)
  results.function_definition_line = def and def.range.start.line

  vim.lsp.stop_client(id)
end

local ok, e = pcall(run)
if not ok then results.error = tostring(e) end
local f = io.open(out, 'w')
f:write(vim.fn.json_encode(results))
f:close()
vim.cmd('qa!')
