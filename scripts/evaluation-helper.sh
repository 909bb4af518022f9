# Sourced by scripts/varobs-transfer.sh (not run on its own).
# evaluate RUN FOLDER [OPTIONS...]: `lanefree evaluate RUN --out RUN/FOLDER` with $episodes episodes unless
# RUN/FOLDER already holds that many; an evaluation stopped part-way (it keeps what it finished) is run again
# whole. Needs $bin (the lanefree command) and $episodes.
evaluate() {
    local run=$1 folder=$2
    shift 2
    local log=$run/$folder/episodes.csv
    if [ -s "$log" ] && [ $(($(wc -l <"$log") - 1)) -ge "$episodes" ]; then return 0; fi
    "$bin" evaluate "$run" --episodes "$episodes" --out "$run/$folder" --overwrite "$@"
}
