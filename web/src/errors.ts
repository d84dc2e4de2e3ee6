// The errors the decoder throws: the classes of dftpcc.errors, so a page or a test can tell a damaged
// file (CorruptFileError) from an allocation bomb (ResourceLimitError, a CorruptFileError too), another
// major version (UnsupportedFormatError) and a caller's bad argument (InvalidInputError).

export class DftpccError extends Error {
  constructor(message: string) {
    super(message);
    this.name = new.target.name;
  }
}

export class InvalidInputError extends DftpccError {}

export class UnsupportedFormatError extends InvalidInputError {}

export class CorruptFileError extends DftpccError {}

export class ResourceLimitError extends CorruptFileError {}

/** Runs `f`, turning anything but a DftpccError (a typed array out of range, a zstd library's own
 * error) into a CorruptFileError named after `what`: a crafted file must never surface as a crash. */
export function guard<T>(what: string, f: () => T): T {
  try {
    return f();
  } catch (exc) {
    if (exc instanceof DftpccError) throw exc;
    throw new CorruptFileError(`${what}: ${exc instanceof Error ? exc.message : String(exc)}`);
  }
}
